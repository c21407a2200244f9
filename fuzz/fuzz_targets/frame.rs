//! Arbitrary bytes as a frame: the first 80 as the header's fields, the rest as points.
//! Validation, then integration of what it accepts into a small map (in the ray mode the
//! second byte picks), must never panic; a rejected frame leaves the map as it was.
#![no_main]

use libfuzzer_sys::fuzz_target;
use voxmap_map::{Frame, Integrator, IntegratorConfig, OccupancyMap, RayMode, SensorModel};
use voxmap_ipc::FrameHeader;

fn u64_at(b: &[u8], i: usize) -> u64 {
    u64::from_le_bytes(b[i..i + 8].try_into().unwrap())
}

fuzz_target!(|data: &[u8]| {
    if data.len() < 80 {
        return;
    }
    let (h, rest) = data.split_at(80);
    let f = |i| f64::from_bits(u64_at(h, i));
    let header = FrameHeader {
        version: u32::from_le_bytes(h[0..4].try_into().unwrap()) % 4,
        flags: u32::from_le_bytes(h[4..8].try_into().unwrap()),
        sequence: u64_at(h, 8),
        timestamp_ns: u64_at(h, 16),
        translation: [f(24), f(32), f(40)],
        rotation_xyzw: [f(48), f(56), f(64), f(72)],
        // The count is the payload's, or a lie, as the first byte says.
        point_count: match h[0] & 3 {
            0 => u64_at(h, 8),
            _ => (rest.len() / 12) as u64,
        },
    };
    let points: Vec<[f32; 3]> = rest
        .chunks_exact(12)
        .map(|c| {
            std::array::from_fn(|k| f32::from_le_bytes(c[4 * k..4 * k + 4].try_into().unwrap()))
        })
        .collect();
    let Ok(pose) = header.validate(points.len()) else {
        return;
    };
    let mut map = OccupancyMap::new(0.25, SensorModel::default()).unwrap();
    // One integrator per mode for every input: making one starts its thread pool.
    const MODES: [RayMode; 4] = [
        RayMode::Exact,
        RayMode::Subsample { factor: 2 },
        RayMode::Bundle { threshold: 2 },
        RayMode::UniqueEnd,
    ];
    static INTEG: std::sync::OnceLock<Vec<std::sync::Mutex<Integrator>>> =
        std::sync::OnceLock::new();
    let integs = INTEG.get_or_init(|| {
        MODES
            .iter()
            .map(|&mode| {
                std::sync::Mutex::new(
                    Integrator::new(IntegratorConfig {
                        threads: 1,
                        max_range: 4.0,
                        pin_threads: false,
                        mode,
                    })
                    .unwrap(),
                )
            })
            .collect()
    });
    let mut integ = integs[usize::from(h[1] & 3)]
        .lock()
        .unwrap_or_else(|e| e.into_inner());
    if integ
        .integrate(
            &mut map,
            &Frame {
                pose,
                points: &points,
            },
        )
        .is_err()
    {
        assert_eq!(
            map.grid().leaf_count(),
            0,
            "a rejected frame changed the map"
        );
    }
});

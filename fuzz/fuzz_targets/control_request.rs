//! Arbitrary bytes as a control request's fields: the service's decoding of it (kind, path,
//! scope, and the scope's box around a sensor) must never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use voxmap_ipc::control::CONTROL_PATH_MAX;
use voxmap_ipc::{ControlKind, ControlRequest};

fuzz_target!(|data: &[u8]| {
    if data.len() < 16 + 48 + 24 {
        return;
    }
    let u = |i: usize| u32::from_le_bytes(data[i..i + 4].try_into().unwrap());
    let f = |i: usize| f64::from_bits(u64::from_le_bytes(data[i..i + 8].try_into().unwrap()));
    let mut r = ControlRequest::new(ControlKind::Stats);
    r.kind = u(0) % 16;
    r.scope_kind = u(4) % 8;
    r.path_len = u(8) % (2 * CONTROL_PATH_MAX as u32);
    r.reserved = u(12);
    r.scope = std::array::from_fn(|k| f(16 + 8 * k));
    let sensor = [f(64), f(72), f(80)];
    let tail = &data[88..];
    let n = tail.len().min(CONTROL_PATH_MAX);
    r.path[..n].copy_from_slice(&tail[..n]);
    let _ = r.kind();
    if let Some(p) = r.path() {
        assert!(p.len() <= CONTROL_PATH_MAX);
    }
    if let Ok(scope) = r.scope() {
        if let Some((lo, hi)) = scope.bounds(sensor) {
            let _ = (lo, hi);
        }
    }
});

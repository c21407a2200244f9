//! The checked-in `include/voxmap.h` is what cbindgen makes of the crate today.
//! `VOXMAP_BLESS=1 cargo test -p voxmap-c --test header` rewrites it.

use std::path::Path;

#[test]
fn header_is_current() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    let config = cbindgen::Config::from_file(dir.join("cbindgen.toml")).expect("cbindgen.toml");
    let mut generated = Vec::new();
    cbindgen::Builder::new()
        .with_crate(dir)
        .with_config(config)
        .generate()
        .expect("cbindgen")
        .write(&mut generated);
    let path = dir.join("include/voxmap.h");
    if std::env::var_os("VOXMAP_BLESS").is_some() {
        std::fs::write(&path, &generated).unwrap();
        return;
    }
    let checked_in = std::fs::read(&path).unwrap_or_default();
    assert!(
        checked_in == generated,
        "include/voxmap.h is stale: run VOXMAP_BLESS=1 cargo test -p voxmap-c --test header"
    );
}

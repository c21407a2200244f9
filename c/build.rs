//! The shared library's soname, so that programs linked against it record `libvoxmap.so`
//! rather than the path it was linked from.
fn main() {
    if std::env::var("CARGO_CFG_TARGET_OS").as_deref() == Ok("linux") {
        println!("cargo:rustc-cdylib-link-arg=-Wl,-soname,libvoxmap.so");
    }
}

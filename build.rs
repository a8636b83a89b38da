//! Build script: `ale-sys` builds the Arcade Learning Environment as a static C++ library but does
//! not link the C++ runtime on Linux, so every binary that uses it would fail to link. We add it.
fn main() {
    let target = std::env::var("TARGET").unwrap_or_default();
    if target.contains("apple") || target.contains("freebsd") {
        println!("cargo:rustc-link-lib=c++");
    } else if !target.contains("msvc") {
        println!("cargo:rustc-link-lib=stdc++");
    }
    println!("cargo:rerun-if-changed=build.rs");
}

//! Builds the Arcade Learning Environment's C library (`ale_c_static`) with the `cc` crate.
//!
//! The published `ale-sys` 0.1.2 drives ALE's `CMakeLists.txt` through the `cmake` crate (target
//! `ale-c-lib-static`, with `USE_SDL=OFF`, `USE_RLGLUE=OFF`, `BUILD_C_LIB=ON`), so building it
//! needs a `cmake` program on the machine. That target is just a list of sources and flags, so
//! this script compiles the same list with the same flags through `cc`, which needs only the C and
//! C++ compilers that a Rust toolchain on Linux has beside it anyway. Vendoring the crate and
//! patching it in (`[patch.crates-io]` in the top-level Cargo.toml) keeps the `ale` crate, its ROM
//! and the Rust bindings exactly as published; a separate build crate would have needed a fork of
//! `ale` as well, since `ale` names `ale-sys` as its dependency.
//!
//! What `CMakeLists.txt` (kept beside the sources for reference, never run) builds for
//! `ale-c-lib-static`, and how it maps here:
//! - sources: every `*.c` and `*.c?[xp]` (`.cpp`, `.cxx`) file directly inside the directories
//!   of `MODULES`, the three `os_dependent/*UNIX`/`*POSIX` files (the `Win32` ones on Windows),
//!   `src/ale_interface.cpp` and the C wrapper `ale_py/ale_c_wrapper.cpp`;
//! - include directories: `src` and the directories listed in `INCLUDE_DIRS` below;
//! - C++ flags: `-std=c++11 -fPIC -O3 -fomit-frame-pointer -D__STDC_CONSTANT_MACROS`, and for
//!   every file `-DHAVE_INTTYPES` (no `__USE_SDL`, no `SOUND_SUPPORT`, no `__USE_RLGLUE`);
//!   C files get only the definitions, as CMake gives them only `CMAKE_C_FLAGS`.
//!
//! Optimisation: always `-O2`, and `NDEBUG` unless the profile has `opt-level = 0`. Under cmake
//! the effective level depended on the profile: this project's release profile has `debug = 1`,
//! which the published build script mapped to CMake's `RelWithDebInfo`, whose `-O2 -g -DNDEBUG`
//! comes after ALE's own `-O3` on the command line, so release builds were `-O2` already; a dev
//! build (`Debug`, `-g`) kept ALE's `-O3`.
//! Unoptimised, the emulator runs several times slower, which would make debug-profile tests
//! that step it crawl; `-O2` everywhere keeps the release build's code as it was and the debug
//! build fast. The debug-information level still follows the profile (cc reads `DEBUG`).
//!
//! Warnings are off: this is third-party code, and its `-Wall` output would be shown on every
//! build because the crate is a path dependency.
//!
//! Linking: `cpp(true)` makes cc emit the link directive for the C++ runtime (`stdc++` on Linux,
//! `c++` on macOS and the BSDs, nothing on MSVC), which the published crate left to its users.
//! The C files are compiled first and their objects added to the C++ archive, so the static
//! library is a single `libale_c_static.a`, as before.

use std::path::{Path, PathBuf};

/// ALE's `MODULES` (CMakeLists.txt): the directories whose sources are compiled.
const MODULES: &[&str] = &[
    "common",
    "controllers",
    "emucore",
    "emucore/m6502/src",
    "emucore/m6502/src/bspf/src",
    "environment",
    "games",
    "games/supported",
    "external",
    "external/TinyMT",
    "external/zlib",
];

/// ALE's `include_directories` besides `src` itself.
const INCLUDE_DIRS: &[&str] = &[
    "common",
    "controllers",
    "emucore",
    "emucore/m6502/src",
    "emucore/m6502/src/bspf/src",
    "environment",
    "games",
    "games/supported",
    "os_dependent",
    "external",
    "external/TinyMT",
    "external/zlib",
];

#[derive(PartialEq)]
enum Lang {
    C,
    Cxx,
}

/// CMake's globs `*.c` and `*.c?[xp]`.
fn language(path: &Path) -> Option<Lang> {
    let ext = path.extension()?.to_str()?.as_bytes();
    match ext {
        b"c" => Some(Lang::C),
        [b'c', _, b'x' | b'p'] => Some(Lang::Cxx),
        _ => None,
    }
}

fn main() {
    let root = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("CARGO_MANIFEST_DIR"));
    let ale = root.join("ale");
    let src = ale.join("src");
    let windows = std::env::var("CARGO_CFG_TARGET_OS").as_deref() == Ok("windows");
    let msvc = std::env::var("CARGO_CFG_TARGET_ENV").as_deref() == Ok("msvc");
    let opt_level_zero = std::env::var("OPT_LEVEL").as_deref() == Ok("0");

    let mut c_files = Vec::new();
    let mut cxx_files = Vec::new();
    for module in MODULES {
        let dir = src.join(module);
        let mut entries: Vec<PathBuf> = std::fs::read_dir(&dir)
            .unwrap_or_else(|e| panic!("cannot read {}: {e}", dir.display()))
            .map(|entry| entry.expect("directory entry").path())
            .filter(|path| path.is_file())
            .collect();
        entries.sort();
        for path in entries {
            match language(&path) {
                Some(Lang::C) => c_files.push(path),
                Some(Lang::Cxx) => cxx_files.push(path),
                None => {}
            }
        }
    }
    let os_dependent: &[&str] = if windows {
        &["SettingsWin32.cxx", "OSystemWin32.cxx", "FSNodeWin32.cxx"]
    } else {
        &["SettingsUNIX.cxx", "OSystemUNIX.cxx", "FSNodePOSIX.cxx"]
    };
    cxx_files.extend(os_dependent.iter().map(|f| src.join("os_dependent").join(f)));
    cxx_files.push(src.join("ale_interface.cpp"));
    cxx_files.push(ale.join("ale_py").join("ale_c_wrapper.cpp"));

    let configure = |build: &mut cc::Build| {
        build
            .include(&src)
            .includes(INCLUDE_DIRS.iter().map(|d| src.join(d)))
            .define("HAVE_INTTYPES", None)
            .opt_level(2)
            .warnings(false)
            .extra_warnings(false);
        if !opt_level_zero {
            build.define("NDEBUG", None);
        }
        if windows {
            // What the published build script passed on Windows.
            build.define("WIN32", "1");
        }
    };

    let mut c = cc::Build::new();
    configure(&mut c);
    c.files(&c_files).cargo_metadata(false);
    let c_objects = c.compile_intermediates();

    let mut cxx = cc::Build::new();
    configure(&mut cxx);
    cxx.cpp(true)
        .files(&cxx_files)
        .objects(c_objects)
        .define("__STDC_CONSTANT_MACROS", None);
    if msvc {
        cxx.std("c++14"); // MSVC's oldest
    } else {
        cxx.std("c++11").flag("-fomit-frame-pointer");
    }
    cxx.compile("ale_c_static");

    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=ale");
}

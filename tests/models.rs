//! A shipped model's folder (`models/strong/`: `model.safetensors` beside its `config.toml`) is
//! taken wherever a network is read, as a run's folder is: `eval`, `export` and
//! `bench --checkpoint`. A folder holding neither network file is refused, naming both.

mod common;

use common::cli::{eval, fails_with, invaders, ok, s, tmp_dir};
use std::path::Path;

const STRONG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/models/strong");

#[test]
fn a_models_folder_is_read_where_a_network_is() {
    let text = eval(Path::new(STRONG), "1");
    assert!(text.contains("preset strong"), "{text}");

    // Export of a model writes the model as it is, once checked.
    let root = tmp_dir("invaders-models", "export");
    let out = root.join("strong.safetensors");
    ok(&invaders(&[
        "export",
        "--checkpoint",
        STRONG,
        "--out",
        s(&out),
    ]));
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(format!("{STRONG}/model.safetensors")).unwrap()
    );

    // bench times acting with it (one step of each kind is enough to show it loads).
    ok(&invaders(&[
        "bench",
        "--threads",
        "1",
        "--steps",
        "1",
        "--checkpoint",
        STRONG,
    ]));

    // A folder with no network names both files it looked for.
    let empty = root.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    for args in [
        vec!["eval", "--checkpoint", s(&empty), "--episodes", "1"],
        vec![
            "export",
            "--checkpoint",
            s(&empty),
            "--out",
            s(&root.join("x.safetensors")),
        ],
    ] {
        fails_with(
            &invaders(&args),
            &[
                "holds no network",
                "checkpoint.safetensors",
                "model.safetensors",
            ],
        );
    }
    let _ = std::fs::remove_dir_all(&root);
}

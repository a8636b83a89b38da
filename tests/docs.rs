//! The documentation names only files and functions that exist.
//!
//! Checked files: `README.md`, `in-progress/README.md` and every `.md` under `docs/` at any
//! depth. What counts as a reference:
//!
//! - **Links.** Every Markdown link or image target `[text](target)` that is not a URL (`://`,
//!   `mailto:`) or a bare `#anchor`. It is resolved against the Markdown file's folder (any
//!   `#anchor` dropped) and must exist inside the repository.
//! - **Paths in code.** In inline code spans and in fenced code blocks, every whitespace-separated
//!   word made only of letters, digits and `_ . - / *`, with at least one `/` and one letter, that
//!   looks like a path: its first component is an entry of the repository's root, or `..`, or
//!   its last component has a file extension (`name.ext`), or it ends in `/`. Words starting with
//!   `/` (an absolute path: the reader's machine) or `runs/` (what the commands write) are left
//!   out; so are, by that rule, formulas such as `x/128` and benchmark filters such as
//!   `sparse_act/conv1`. It is resolved against the repository root and must exist inside the
//!   repository (a folder must hold a file: git keeps no empty folder, so a clone lacks it): a path through `../` to a neighbour that a clone does not have fails. In a
//!   page below `docs/` (a records folder's README), a path that exists relative to the page's
//!   own folder passes too. A word
//!   ending in `/` must be a folder; a `*` in the last component must match at least one file.
//! - **Examples and benchmarks.** Every `--example NAME` and `--bench NAME` must name
//!   `examples/NAME.rs` or `benches/NAME.rs`.
//! - **Functions.** An inline code span written `fn name`, `name(…)` or `Type::name` (a
//!   lower-case `name`, optionally followed by `(…)`) names a function (so formulas in the docs
//!   are written without that form, e.g. `⌊x/3⌋` rather than a floor call): some `.rs` file of the
//!   tree (`src/`, `tests/`, `benches/`, `examples/`, `fuzz/`) must define `fn name`, and for
//!   `Type::name` that file must also have an `impl` line naming `Type`. A path whose first
//!   segment is a lower-case name other than `invaders`, `crate` or a module under `src/` is
//!   another crate's, and is not checked.
//!
//! A renamed file or function fails the test with the Markdown file and the stale reference.
//!
//! And the configuration files under `docs/` and `models/` are ones `--config` accepts
//! ([`every_shipped_config_file_resolves`]).

use std::collections::BTreeSet;
use std::path::{Component, Path, PathBuf};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `README.md`, `in-progress/README.md` and every `.md` under `docs/` at any depth (the records
/// folders' READMEs included), relative to the root.
fn documents() -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        for entry in std::fs::read_dir(dir).expect("a readable folder") {
            let path = entry.expect("entry").path();
            if path.is_dir() {
                walk(&path, out);
            } else if path.extension().is_some_and(|e| e == "md") {
                out.push(
                    path.strip_prefix(root())
                        .expect("under the root")
                        .to_path_buf(),
                );
            }
        }
    }
    let mut docs = vec![PathBuf::from("README.md")];
    if root().join("in-progress/README.md").is_file() {
        docs.push(PathBuf::from("in-progress/README.md"));
    }
    let mut more = Vec::new();
    walk(&root().join("docs"), &mut more);
    more.sort();
    docs.extend(more);
    docs
}

/// A Markdown file split into prose (code blocks removed) and the contents of its fenced blocks.
struct Parsed {
    prose: String,
    blocks: String,
}

fn parse(text: &str) -> Parsed {
    let (mut prose, mut blocks, mut in_block) = (String::new(), String::new(), false);
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            in_block = !in_block;
            prose.push('\n');
            continue;
        }
        let out = if in_block { &mut blocks } else { &mut prose };
        out.push_str(line);
        out.push('\n');
    }
    Parsed { prose, blocks }
}

/// Inline code spans of the prose (single backticks; a span may run over a line break).
fn code_spans(prose: &str) -> Vec<String> {
    let mut spans = Vec::new();
    let mut parts = prose.split('`');
    parts.next();
    while let (Some(span), Some(_)) = (parts.next(), parts.next()) {
        spans.push(span.replace('\n', " "));
    }
    spans
}

/// Link and image targets `](target)` of the prose.
fn link_targets(prose: &str) -> Vec<String> {
    prose
        .match_indices("](")
        .filter_map(|(i, _)| {
            let rest = &prose[i + 2..];
            rest.find(')').map(|end| rest[..end].trim().to_string())
        })
        .collect()
}

fn is_path_word(w: &str) -> bool {
    w.contains('/')
        && w.chars().any(|c| c.is_ascii_alphabetic())
        && w.chars()
            .all(|c| c.is_ascii_alphanumeric() || "_.-/*".contains(c))
        && !w.starts_with('/')
        && !w.starts_with("runs/")
        && {
            let first = w.split('/').next().unwrap_or_default();
            let last = w.rsplit('/').next().unwrap_or_default();
            let has_extension = last.rsplit_once('.').is_some_and(|(stem, ext)| {
                !stem.is_empty()
                    && !ext.is_empty()
                    && ext.chars().all(|c| c.is_ascii_alphanumeric())
                    && ext.chars().any(|c| c.is_ascii_alphabetic())
            });
            w.ends_with('/')
                || has_extension
                || first == ".."
                || (!first.is_empty() && root().join(first).exists())
        }
}

/// `base.join(rel)` with `.` and `..` folded, or `None` if it leaves the repository.
fn resolve(base: &Path, rel: &str) -> Option<PathBuf> {
    let mut out: Vec<String> = base
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    for c in Path::new(rel).components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                out.pop()?;
            }
            Component::Normal(s) => out.push(s.to_string_lossy().into_owned()),
            _ => return None,
        }
    }
    Some(out.iter().collect())
}

/// Whether `rel` (relative to the root) exists, with the rules of the module doc.
fn exists(rel: &Path, want_dir: bool) -> bool {
    let full = root().join(rel);
    let name = rel.file_name().map(|n| n.to_string_lossy().into_owned());
    match name {
        Some(name) if name.contains('*') => {
            let (prefix, suffix) = name.split_once('*').expect("a star");
            let dir = full.parent().expect("a parent");
            std::fs::read_dir(dir).is_ok_and(|entries| {
                entries.filter_map(Result::ok).any(|e| {
                    let n = e.file_name().to_string_lossy().into_owned();
                    n.starts_with(prefix) && n.ends_with(suffix) && n.len() >= name.len() - 1
                })
            })
        }
        _ if full.is_dir() => holds_a_file(&full),
        _ if want_dir => false,
        _ => full.exists(),
    }
}

/// Whether the folder holds a file at some depth: git keeps no empty folder, so a clone (and CI)
/// has only the folders that hold files.
fn holds_a_file(dir: &Path) -> bool {
    std::fs::read_dir(dir).is_ok_and(|entries| {
        entries
            .filter_map(Result::ok)
            .any(|e| !e.path().is_dir() || holds_a_file(&e.path()))
    })
}

fn check_path(doc: &Path, base: &Path, word: &str, errors: &mut Vec<String>) {
    match resolve(base, word.trim_end_matches('/')) {
        None => errors.push(format!(
            "{}: `{word}` is outside the repository",
            doc.display()
        )),
        Some(rel) if !exists(&rel, word.ends_with('/')) => {
            errors.push(format!("{}: `{word}` does not exist", doc.display()))
        }
        Some(_) => {}
    }
}

/// Every `.rs` file of the tree, with its text.
fn sources() -> Vec<(PathBuf, String)> {
    fn walk(dir: &Path, out: &mut Vec<(PathBuf, String)>) {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for e in entries.filter_map(Result::ok) {
            let p = e.path();
            if p.is_dir() {
                if !p.ends_with("target") {
                    walk(&p, out);
                }
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push((p.clone(), std::fs::read_to_string(&p).unwrap_or_default()));
            }
        }
    }
    let mut out = Vec::new();
    for dir in ["src", "tests", "benches", "examples", "fuzz"] {
        walk(&root().join(dir), &mut out);
    }
    out
}

fn is_ident(s: &str) -> bool {
    !s.is_empty()
        && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        && !s.starts_with(|c: char| c.is_ascii_digit())
}

/// The function a code span names, as (qualifying segments, name), if it is written as one.
fn function_ref(span: &str) -> Option<(Vec<String>, String)> {
    let span = span.trim();
    let (span, marked) = match span.strip_prefix("fn ") {
        Some(rest) => (rest.trim(), true),
        None => (span, false),
    };
    let (path, called) = match span.find('(') {
        Some(i) if span.ends_with(')') => (&span[..i], true),
        Some(_) => return None,
        None => (span, false),
    };
    let mut segments: Vec<String> = path.split("::").map(str::to_string).collect();
    let name = segments.pop()?;
    if !is_ident(&name) || name.starts_with(|c: char| c.is_ascii_uppercase()) {
        return None;
    }
    if !segments.iter().all(|s| is_ident(s)) {
        return None;
    }
    let qualified = segments
        .last()
        .is_some_and(|s| s.starts_with(|c: char| c.is_ascii_uppercase()));
    (marked || called || qualified).then_some((segments, name))
}

fn defines_fn(text: &str, name: &str) -> bool {
    text.match_indices(&format!("fn {name}")).any(|(i, m)| {
        let next = text[i + m.len()..].chars().next();
        let before = text[..i].chars().next_back();
        matches!(next, Some('(' | '<'))
            && !before.is_some_and(|c| c.is_ascii_alphanumeric() || c == '_')
    })
}

fn has_impl_of(text: &str, ty: &str) -> bool {
    text.lines().any(|line| {
        let line = line.trim_start();
        line.starts_with("impl")
            && line
                .split(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
                .any(|w| w == ty)
    })
}

fn check_function(
    doc: &Path, span: &str, segments: &[String], name: &str, sources: &[(PathBuf, String)],
    errors: &mut Vec<String>,
) {
    if let Some(first) = segments.first() {
        let local = first == "invaders"
            || first == "crate"
            || first.starts_with(|c: char| c.is_ascii_uppercase())
            || root().join("src").join(format!("{first}.rs")).exists()
            || root().join("src").join(first).is_dir();
        if !local {
            return;
        }
    }
    let ty = segments
        .last()
        .filter(|s| s.starts_with(|c: char| c.is_ascii_uppercase()));
    let found = sources
        .iter()
        .any(|(_, text)| defines_fn(text, name) && ty.is_none_or(|ty| has_impl_of(text, ty)));
    if !found {
        errors.push(format!(
            "{}: `{span}` names no function of the tree",
            doc.display()
        ));
    }
}

/// Every reference of one document that fails, as messages.
fn stale_references(doc: &Path, text: &str, sources: &[(PathBuf, String)]) -> Vec<String> {
    let mut errors = Vec::new();
    let parsed = parse(text);
    let base = doc.parent().unwrap_or(Path::new(""));
    for target in link_targets(&parsed.prose) {
        if target.contains("://") || target.starts_with("mailto:") || target.starts_with('#') {
            continue;
        }
        let target = target.split('#').next().unwrap_or_default();
        check_path(doc, base, target, &mut errors);
    }
    let spans = code_spans(&parsed.prose);
    let words = spans
        .iter()
        .flat_map(|s| s.split_whitespace())
        .chain(parsed.blocks.split_whitespace());
    let words: Vec<&str> = words.collect();
    for w in &words {
        if is_path_word(w) {
            // A records README below `docs/` names its own files (`strong-seed1/result.toml`)
            // from its folder; every other path is the repository's.
            let own = base.components().count() > 1
                && resolve(base, w.trim_end_matches('/'))
                    .is_some_and(|rel| exists(&rel, w.ends_with('/')));
            if !own {
                check_path(doc, Path::new(""), w, &mut errors);
            }
        }
    }
    for pair in words.windows(2) {
        let folder = match pair[0] {
            "--example" => "examples",
            "--bench" => "benches",
            _ => continue,
        };
        if !root()
            .join(folder)
            .join(format!("{}.rs", pair[1]))
            .is_file()
        {
            errors.push(format!(
                "{}: `{} {}` names no {folder}/{}.rs",
                doc.display(),
                pair[0],
                pair[1],
                pair[1]
            ));
        }
    }
    for span in &spans {
        if let Some((segments, name)) = function_ref(span) {
            check_function(doc, span, &segments, &name, sources, &mut errors);
        }
    }
    errors
}

#[test]
fn every_quoted_path_and_function_exists() {
    let sources = sources();
    let mut errors = Vec::new();
    let mut checked = BTreeSet::new();
    for doc in documents() {
        let text = std::fs::read_to_string(root().join(&doc)).expect("readable");
        errors.extend(stale_references(&doc, &text, &sources));
        checked.insert(doc);
    }
    assert!(checked.len() >= 2, "README.md and docs/*.md: {checked:?}");
    assert!(
        errors.is_empty(),
        "stale references:\n{}",
        errors.join("\n")
    );
}

/// The checker itself: each kind of stale reference is caught, and what exists passes.
#[test]
fn the_checker_catches_renamed_files_and_functions() {
    let sources = sources();
    let doc = Path::new("docs/example.md");
    let bad = [
        "[a link](walkthrough-renamed.md)",
        "see `src/tensor/gather_renamed.rs`",
        "a folder `src/nowhere/`",
        "```sh\ncargo run --release -- plot tools/missing.py\n```",
        "```sh\ncargo run --release --example no_such_example\n```",
        "`cargo bench --bench no_such_bench`",
        "`../shared/bench/tf_step.py`",
        "`src/tensor/nothing`",
        "`tools/renamed/`",
        "`no_such_function()`",
        "`fn no_such_function`",
        "`Conv2d::no_such_method`",
        "`NoSuchType::forward`",
    ];
    for text in bad {
        assert!(
            !stale_references(doc, text, &sources).is_empty(),
            "not caught: {text}"
        );
    }
    // A folder that exists here but holds no file is absent from a clone: caught too.
    let empty = root().join("target/docs-checker-empty");
    std::fs::create_dir_all(&empty).expect("a scratch folder under target/");
    for text in [
        "`target/docs-checker-empty`",
        "`target/docs-checker-empty/`",
    ] {
        assert!(
            !stale_references(doc, text, &sources).is_empty(),
            "not caught: {text}"
        );
    }
    let good = [
        "[a link](walkthrough.md) and [another](../README.md#the-two-commands)",
        "`src/tensor/gather.rs`, `src/tensor/`, `docs/*.md`, `runs/anything/`, `/tmp/x.toml`",
        "```sh\ncargo run --release --example replay_memory -- 1000000 --out runs/x\n```",
        "`article_qnet()`, `fn moving_average`, `Conv2d::with_winograd`, `Sequential::infer`",
        "`x/128 − 1`, `plotters::style::register_font`, `double_dqn = true`, `[in, out]`",
        "`cargo bench --bench layers -- sparse_act/conv1`, `⌊(R + G + B)/3⌋`",
    ];
    for text in good {
        let errors = stale_references(doc, text, &sources);
        assert!(errors.is_empty(), "{text}: {errors:?}");
    }
}

/// Every `.toml` file `path` holds, recursively, relative to the root, but the experiment
/// records' `result.toml` (scores and counters, not a configuration).
fn toml_files(path: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(root().join(path)).expect("readable folder") {
        let name = path.join(entry.expect("readable entry").file_name());
        if root().join(&name).is_dir() {
            toml_files(&name, out);
        } else if name.extension().is_some_and(|e| e == "toml")
            && name.file_name().is_some_and(|n| n != "result.toml")
        {
            out.push(name);
        }
    }
}

/// The configuration files the repository ships (lever files, experiment records, the shipped
/// model's) are ones `--config` accepts: a misspelt key or an out-of-range value in a committed
/// file fails here, not hours into someone's run. A file that names no preset is resolved on
/// `strong` and on `strong-v1`, as `invaders experiment strong [--preset strong-v1] --config
/// FILE` applies the lever files (the others that name none set only keys every preset takes);
/// a record names its own.
#[test]
fn every_shipped_config_file_resolves() {
    use invaders::dqn::{Config, Preset};
    let mut files = Vec::new();
    toml_files(Path::new("docs"), &mut files);
    toml_files(Path::new("models"), &mut files);
    let mut errors = Vec::new();
    for f in &files {
        let text = std::fs::read_to_string(root().join(f)).expect("readable");
        let named = text.lines().any(|l| l.trim_start().starts_with("preset"));
        let presets = match named {
            true => vec![None],
            false => vec![Some(Preset::Strong), Some(Preset::StrongV1)],
        };
        for preset in presets {
            if let Err(e) = Config::resolve(preset, Some(&text)) {
                errors.push(format!("{}: {e:#}", f.display()));
            }
        }
    }
    assert!(files.len() >= 10, "config files found: {files:?}");
    assert!(errors.is_empty(), "{}", errors.join("\n"));
}

/// The pages stay short enough to read, and the index reaches them all (issue #96):
/// - no page over 600 lines, and `docs/strong.md` (the `strong` presets: the table of levers
///   and the commands; each run's story lives in its records folder) at most 300;
/// - `README.md` at most 10 240 bytes, with the two commands (the training run and the tests)
///   in its first 40 lines;
/// - every `.md` under `docs/` reached from `docs/README.md` by following links between pages.
#[test]
fn pages_stay_short() {
    let mut errors = Vec::new();
    for doc in documents() {
        let text = std::fs::read_to_string(root().join(&doc)).expect("readable");
        let lines = text.lines().count();
        let limit = if doc == Path::new("docs/strong.md") {
            300
        } else {
            600
        };
        if lines > limit {
            errors.push(format!("{}: {lines} lines, over {limit}", doc.display()));
        }
    }
    let readme = std::fs::read_to_string(root().join("README.md")).expect("README.md");
    if readme.len() > 10_240 {
        errors.push(format!("README.md: {} bytes, over 10 240", readme.len()));
    }
    let head: String = readme.lines().take(40).collect::<Vec<_>>().join("\n");
    for command in ["cargo run --release -- train", "cargo test --release"] {
        if !head.contains(command) {
            errors.push(format!(
                "README.md: `{command}` is not in its first 40 lines"
            ));
        }
    }
    // Every page under docs/ is reached from the index through links between Markdown pages.
    let mut reached = BTreeSet::new();
    let mut todo = vec![PathBuf::from("docs/README.md")];
    while let Some(page) = todo.pop() {
        if !reached.insert(page.clone()) {
            continue;
        }
        let Ok(text) = std::fs::read_to_string(root().join(&page)) else {
            continue;
        };
        let base = page.parent().unwrap_or(Path::new("")).to_path_buf();
        for target in link_targets(&parse(&text).prose) {
            if target.contains("://") || target.starts_with('#') {
                continue;
            }
            let target = target.split('#').next().unwrap_or_default();
            if let Some(rel) = resolve(&base, target) {
                let rel = if root().join(&rel).is_dir() {
                    rel.join("README.md")
                } else {
                    rel
                };
                if rel.extension().is_some_and(|e| e == "md") && rel.starts_with("docs") {
                    todo.push(rel);
                }
            }
        }
    }
    for doc in documents() {
        if doc.starts_with("docs") && !reached.contains(&doc) {
            errors.push(format!(
                "{}: no chain of links from docs/README.md reaches it",
                doc.display()
            ));
        }
    }
    assert!(errors.is_empty(), "{}", errors.join("\n"));
}

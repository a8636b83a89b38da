//! Configuration errors that say where: a range error of `Config::validate` names the key, and
//! this adds the line of the user's file that set it, and writes huge numbers short.

use std::path::Path;

use anyhow::anyhow;
use invaders::dqn::{Config, Preset};

/// `v` as a message shows it: as is up to 30 digits (every integer a knob takes stays exact),
/// else in scientific notation (`1e300`, not three hundred digits).
pub fn short_number(v: f64) -> String {
    let plain = v.to_string();
    if plain.chars().filter(char::is_ascii_digit).count() <= LONG {
        plain
    } else {
        format!("{v:e}")
    }
}

/// The most digits a number is shown with.
const LONG: usize = 30;

/// `msg` with every number of more than 30 digits written short ([`short_number`]).
pub fn shorten_numbers(msg: &str) -> String {
    let mut out = String::with_capacity(msg.len());
    let mut rest = msg;
    while let Some(start) = rest.find(|c: char| c.is_ascii_digit()) {
        out.push_str(&rest[..start]);
        let tail = &rest[start..];
        let len = tail
            .find(|c: char| !(c.is_ascii_digit() || c == '.'))
            .unwrap_or(tail.len());
        let number = tail[..len].trim_end_matches('.');
        let digits = number.chars().filter(char::is_ascii_digit).count();
        match number.parse::<f64>() {
            Ok(v) if digits > LONG => out.push_str(&short_number(v)),
            _ => out.push_str(number),
        }
        rest = &tail[number.len()..];
    }
    out.push_str(rest);
    out
}

/// A configuration error `e` (of `Config::validate`, whose messages start with the key, as
/// `gamma must be …` or `pqn.games must be …`) with the line of `text`, the file `file`, that
/// sets that key, where it does, and its huge numbers written short.
pub fn locate(e: anyhow::Error, text: &str, file: &Path) -> anyhow::Error {
    let msg = shorten_numbers(&format!("{e:#}"));
    let key: String = msg
        .chars()
        .take_while(|c| c.is_ascii_alphanumeric() || *c == '_' || *c == '.')
        .collect();
    let (table, name) = match key.split_once('.') {
        Some((t, k)) => (Some(t), k),
        None => (None, key.as_str()),
    };
    let mut current: Option<String> = None;
    for (n, line) in text.lines().enumerate() {
        let l = line.trim();
        if let Some(t) = l.strip_prefix('[') {
            current = Some(t.trim_end_matches(']').trim().to_string());
            continue;
        }
        let at_key = l.split('=').next().is_some_and(|k| k.trim() == name) && l.contains('=');
        let in_table = match table {
            Some(t) => current.as_deref() == Some(t),
            None => true,
        };
        if !name.is_empty() && at_key && in_table {
            return anyhow!("{}, line {}: {msg}", file.display(), n + 1);
        }
    }
    anyhow!("{msg}")
}

/// [`Config::resolve`] of `preset` overlaid with `text`, read from the `--config` file `path`
/// (none: no file): an error names the file's line and key where it can ([`locate`]), as for
/// every command that takes `--config` (`train`, `bench`, the experiments).
pub fn resolve_file(
    preset: Option<Preset>, text: &str, path: Option<&Path>,
) -> anyhow::Result<Config> {
    Config::resolve(preset, Some(text)).map_err(|e| locate(e, text, path.unwrap_or(Path::new(""))))
}

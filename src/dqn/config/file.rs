//! A configuration file read onto a preset: the TOML is parsed, its keys merged over the
//! preset's, and an invalid file is reported by the line and key that make it so.

use super::*;

impl Config {
    /// Resolves a configuration: the preset (`preset`, else the file's `preset` key, else
    /// `article`), overlaid with the keys of `toml_text`. Unknown keys are errors.
    pub fn resolve(preset: Option<Preset>, toml_text: Option<&str>) -> anyhow::Result<Config> {
        let file: toml::Table = match toml_text {
            Some(t) => toml::from_str(t).context("config file is not valid TOML")?,
            None => toml::Table::new(),
        };
        let file_preset = match file.get("preset") {
            Some(v) => Some(
                Preset::deserialize(v.clone())
                    .map_err(|e| anyhow::anyhow!("config key `preset`: {e}"))?,
            ),
            None => None,
        };
        let p = preset.or(file_preset).unwrap_or_default();
        let mut base = toml::Table::try_from(Config::preset(p)).expect("a config serialises");
        // Choosing a game mode sets that mode's knobs; the file's own knobs then override them.
        if let Some(mode) = file
            .get("env")
            .and_then(|e| e.as_table())
            .and_then(|e| e.get("mode"))
        {
            let mode = EnvMode::deserialize(mode.clone())
                .map_err(|e| anyhow::anyhow!("config key `env.mode`: {e}"))?;
            base.insert(
                "env".into(),
                toml::Value::try_from(Config::preset(p).env.with_mode(mode))
                    .expect("an env config serialises"),
            );
        }
        merge_toml(&mut base, file.clone());
        base.insert("preset".into(), toml::Value::String(p.name().into()));
        // Deserialising from text (not from the table) makes errors quote the offending line.
        let merged = toml::to_string(&base).expect("a table serialises");
        let config: Config = match toml::from_str(&merged) {
            Ok(c) => c,
            // The merged document's line numbers mean nothing to the user: name their key.
            Err(e) => bail!(
                "{}",
                culprit(&file, toml_text.unwrap_or(""), p, e.message())
                    .unwrap_or_else(|| e.message().to_string())
            ),
        };
        config.validate()?;
        Ok(config)
    }
}

/// The first key of the user's `file` that makes the configuration invalid on its own with the
/// error `whole` of the whole file, as `line N: key `k`: what is wrong`, with the line of the
/// user's `text`. A key whose error alone differs from the whole file's (`frame_skip_min = 5`
/// against the preset's maximum, where the file also sets `frame_skip_max = 2`) is not the
/// culprit: the message would quote values the user never wrote.
fn culprit(file: &toml::Table, text: &str, p: Preset, whole: &str) -> Option<String> {
    let mut keys: Vec<(Option<&str>, &str, &toml::Value)> = Vec::new();
    for (k, v) in file {
        match v.as_table() {
            Some(t) if k == "env" => {
                keys.extend(t.iter().map(|(k2, v2)| (Some("env"), k2.as_str(), v2)))
            }
            _ => keys.push((None, k.as_str(), v)),
        }
    }
    for (table, key, value) in keys {
        let mut base = toml::Table::try_from(Config::preset(p)).ok()?;
        let target = match table {
            Some(t) => base.get_mut(t)?.as_table_mut()?,
            None => &mut base,
        };
        target.insert(key.to_string(), value.clone());
        let text_one = toml::to_string(&base).ok()?;
        if let Err(e) = toml::from_str::<Config>(&text_one) {
            if e.message() != whole {
                continue;
            }
            let name = table.map_or(key.to_string(), |t| format!("{t}.{key}"));
            return Some(match key_line(text, table, key) {
                Some(line) => format!("line {line}: key `{name}`: {}", e.message()),
                None => format!("key `{name}`: {}", e.message()),
            });
        }
    }
    None
}

/// The line (from 1) of `text` that sets `key`, in the table `table` (`None`: the top level).
fn key_line(text: &str, table: Option<&str>, key: &str) -> Option<usize> {
    let mut current: Option<String> = None;
    for (i, line) in text.lines().enumerate() {
        let t = line.trim();
        if let Some(name) = t.strip_prefix('[').and_then(|r| r.strip_suffix(']')) {
            current = Some(name.trim().to_string());
            continue;
        }
        let Some((k, _)) = t.split_once('=') else {
            continue;
        };
        let k = k.trim().trim_matches('"');
        let (in_table, k) = match k.split_once('.') {
            Some((t, k)) if current.is_none() => (Some(t.trim().to_string()), k.trim()),
            _ => (current.clone(), k),
        };
        if k == key && in_table.as_deref() == table {
            return Some(i + 1);
        }
    }
    None
}

/// Overlays `top` on `base`, recursing into tables (so `[env]` keys override one by one).
pub fn merge_toml(base: &mut toml::Table, top: toml::Table) {
    for (k, v) in top {
        match (base.get_mut(&k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(t)) => merge_toml(b, t),
            (_, v) => {
                base.insert(k, v);
            }
        }
    }
}

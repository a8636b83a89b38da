//! How the game is played: frame skip, sticky actions, episode limits. Three named modes give the
//! settings of well-known setups; every knob can also be set on its own.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use super::preprocess::{Crop, Downsample};
use super::EnvError;

/// The most emulator frames one agent step may repeat an action for.
pub const MAX_FRAME_SKIP: u32 = 100;
/// The most no-op frames a reset may play.
pub const MAX_NOOPS: u32 = 10_000;
/// The longest episode cut a configuration may ask for, in agent steps; an episode without a
/// configured cut is cut here too (about 60 hours of play at 4 frames a step), so that no game,
/// however broken, plays forever.
pub const MAX_EPISODE_STEPS: u32 = 1_000_000;

/// A named set of environment settings.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum EnvMode {
    /// Gym's `SpaceInvaders-v0`, which the article used: each agent step repeats the action for
    /// 2, 3 or 4 frames (drawn uniformly every step), actions are sticky with probability 0.25,
    /// and an episode is cut after 10 000 agent steps.
    #[default]
    V0,
    /// The Nature DQN setup (Mnih et al. 2015): 4 frames per step, the observation is the
    /// element-wise max of the last two frames, no sticky actions, and up to 30 no-op frames at
    /// the start of each episode so games do not all start identically.
    Nature,
    /// Gym's `ALE/SpaceInvaders-v5` (Machado et al. 2018): 4 frames per step, sticky actions
    /// with probability 0.25, episodes cut after 27 000 agent steps (108 000 frames).
    V5,
}

/// All settings of a [`SpaceInvaders`](super::SpaceInvaders) environment.
///
/// Deserialisation fills every field that is missing from the defaults of `mode` (itself `v0`
/// when missing), then validates, so `{"mode": "nature", "noop_max": 0}` is a valid config.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "PartialEnvConfig")]
pub struct EnvConfig {
    /// The mode the defaults came from (informative once knobs are changed).
    pub mode: EnvMode,
    /// Fewest emulator frames per agent step (at least 1).
    pub frame_skip_min: u32,
    /// Most emulator frames per agent step; each step draws uniformly in `min..=max`.
    pub frame_skip_max: u32,
    /// Probability, per emulator frame, that the previous action is repeated instead of the new
    /// one ("sticky actions"), in [0, 1].
    pub sticky_prob: f64,
    /// If true, [`observation`](super::SpaceInvaders::observation) is the element-wise max of the
    /// last two raw frames of the step; otherwise it is the last frame.
    pub max_pool_last_two: bool,
    /// At reset, play a uniformly random number of no-op frames in `0..=noop_max`.
    pub noop_max: u32,
    /// Cut episodes after this many agent steps (reported as `truncated`); `None` for no cut,
    /// written `0` in a config file (TOML has no null).
    #[serde(serialize_with = "none_as_zero")]
    pub max_episode_steps: Option<u32>,
    /// Use all 18 joystick actions instead of the game's 6 meaningful ones.
    pub full_action_set: bool,
    /// A Space Invaders ROM to use instead of the bundled one.
    pub rom: Option<PathBuf>,
    /// The article's contrast step: pixels whose `R + G + B` equals this become 0. `None` (the
    /// default) disables it; the article's value is [`MSPACMAN_RGB_SUM`](super::MSPACMAN_RGB_SUM),
    /// which never occurs in Space Invaders.
    pub contrast_rgb_sum: Option<u16>,
    /// How each 2 x 2 pixel block becomes one pixel of the 88 x 80 frame: `pick` its top-left
    /// pixel (the article's, and the default) or its `max` (keeps one-pixel-wide shots).
    pub downsample: Downsample,
    /// Which screen rows become the frame's 88: the article's (the default), or the `mothership`
    /// crop that also keeps the band the mothership flies in.
    pub crop: Crop,
    /// Let ALE print its informational console output.
    pub ale_verbose: bool,
}

impl EnvConfig {
    /// The settings of a named mode (bundled ROM, minimal action set, ALE quiet).
    pub fn from_mode(mode: EnvMode) -> Self {
        let base = EnvConfig {
            mode,
            frame_skip_min: 4,
            frame_skip_max: 4,
            sticky_prob: 0.0,
            max_pool_last_two: false,
            noop_max: 0,
            max_episode_steps: None,
            full_action_set: false,
            rom: None,
            contrast_rgb_sum: None,
            downsample: Downsample::Pick,
            crop: Crop::Article,
            ale_verbose: false,
        };
        match mode {
            EnvMode::V0 => EnvConfig {
                frame_skip_min: 2,
                frame_skip_max: 4,
                sticky_prob: 0.25,
                max_episode_steps: Some(10_000),
                ..base
            },
            EnvMode::Nature => EnvConfig {
                max_pool_last_two: true,
                noop_max: 30,
                ..base
            },
            EnvMode::V5 => EnvConfig {
                sticky_prob: 0.25,
                max_episode_steps: Some(27_000),
                ..base
            },
        }
    }

    /// `mode`'s dynamics (frame skip, sticky actions, max-pool, no-ops, episode cut, action set)
    /// with this configuration's preprocessing (`contrast_rgb_sum`, `downsample`, `crop`), ROM and
    /// verbosity: what choosing a game mode changes, for a run or an evaluation.
    pub fn with_mode(&self, mode: EnvMode) -> EnvConfig {
        EnvConfig {
            rom: self.rom.clone(),
            contrast_rgb_sum: self.contrast_rgb_sum,
            downsample: self.downsample,
            crop: self.crop,
            ale_verbose: self.ale_verbose,
            ..EnvConfig::from_mode(mode)
        }
    }

    /// The game an evaluation in `mode` plays: `mode`'s dynamics ([`EnvConfig::with_mode`]),
    /// but the frames the network sees made as in training. Max-pooling the last two frames
    /// changes no dynamics, only what the network sees (Space Invaders draws some shots on
    /// alternate frames, `examples/flicker.rs`): a network trained on pooled frames is evaluated
    /// on pooled frames, whatever the mode, and one trained without, without.
    pub fn for_evaluation(&self, mode: EnvMode) -> EnvConfig {
        EnvConfig {
            max_pool_last_two: self.max_pool_last_two,
            ..self.with_mode(mode)
        }
    }

    /// Checks that every value is in range.
    pub fn validate(&self) -> Result<(), EnvError> {
        let bad = |m: String| Err(EnvError::InvalidConfig(m));
        if self.frame_skip_min == 0 {
            return bad("frame_skip_min must be at least 1".into());
        }
        if self.frame_skip_min > self.frame_skip_max {
            return bad(format!(
                "frame_skip_min ({}) is larger than frame_skip_max ({})",
                self.frame_skip_min, self.frame_skip_max
            ));
        }
        if !(0.0..=1.0).contains(&self.sticky_prob) {
            return bad(format!(
                "sticky_prob must be in [0, 1], got {}",
                self.sticky_prob
            ));
        }
        if self.max_episode_steps == Some(0) {
            return bad(
                "max_episode_steps must be at least 1 (or 0 in a config file for no limit)".into(),
            );
        }
        // Bounds a real run could use: beyond them a step or a reset would take hours.
        if self.frame_skip_max > MAX_FRAME_SKIP {
            return bad(format!(
                "frame_skip_max must be at most {MAX_FRAME_SKIP}, got {}",
                self.frame_skip_max
            ));
        }
        if self.noop_max > MAX_NOOPS {
            return bad(format!(
                "noop_max must be at most {MAX_NOOPS}, got {}",
                self.noop_max
            ));
        }
        if self
            .max_episode_steps
            .is_some_and(|n| n > MAX_EPISODE_STEPS)
        {
            return bad(format!(
                "max_episode_steps must be at most {MAX_EPISODE_STEPS} (0 for no limit), got {}",
                self.max_episode_steps.unwrap_or(0)
            ));
        }
        if self.contrast_rgb_sum.is_some_and(|s| s > 765) {
            return bad("contrast_rgb_sum must be at most 765 (= 3 * 255)".into());
        }
        Ok(())
    }

    /// The settings that shape the game's dynamics, as text; a saved state records it so it is
    /// not restored into a differently configured environment. (The ROM path and verbosity may
    /// differ; the mode label is ignored as only the knobs matter. The downsampling and the crop
    /// are named only when they are not the default, so the fingerprints of earlier checkpoints
    /// still match.)
    pub(crate) fn dynamics_fingerprint(&self) -> String {
        let downsample = match self.downsample {
            Downsample::Pick => String::new(),
            d => format!(" downsample={d:?}"),
        };
        let crop = match self.crop {
            Crop::Article => String::new(),
            c => format!(" crop={c:?}"),
        };
        format!(
            "skip={}..={} sticky={} maxpool={} noop={} limit={:?} full={} contrast={:?}{downsample}{crop}",
            self.frame_skip_min,
            self.frame_skip_max,
            self.sticky_prob,
            self.max_pool_last_two,
            self.noop_max,
            self.max_episode_steps,
            self.full_action_set,
            self.contrast_rgb_sum
        )
    }
}

impl Default for EnvConfig {
    fn default() -> Self {
        EnvConfig::from_mode(EnvMode::V0)
    }
}

/// What may be written in a config file: everything optional except that `mode` picks defaults.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PartialEnvConfig {
    #[serde(default)]
    mode: EnvMode,
    frame_skip_min: Option<u32>,
    frame_skip_max: Option<u32>,
    sticky_prob: Option<f64>,
    max_pool_last_two: Option<bool>,
    noop_max: Option<u32>,
    #[serde(default, deserialize_with = "present_zero_none")]
    max_episode_steps: Option<Option<u32>>,
    full_action_set: Option<bool>,
    #[serde(default, deserialize_with = "present")]
    rom: Option<Option<PathBuf>>,
    #[serde(default, deserialize_with = "present")]
    contrast_rgb_sum: Option<Option<u16>>,
    downsample: Option<Downsample>,
    crop: Option<Crop>,
    ale_verbose: Option<bool>,
}

/// Writes `None` as 0 (TOML has no null), so `config.toml` says "no cut" where there is none.
fn none_as_zero<S: serde::Serializer>(v: &Option<u32>, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_u32(v.unwrap_or(0))
}

/// Like [`present`], with 0 also meaning `None` (no episode cut).
fn present_zero_none<'de, D>(d: D) -> Result<Option<Option<u32>>, D::Error>
where
    D: serde::Deserializer<'de>,
{
    Option::<u32>::deserialize(d).map(|v| Some(v.filter(|&n| n > 0)))
}

/// Distinguishes a field given as `null` (`Some(None)`) from a missing one (`None`).
fn present<'de, D, T>(d: D) -> Result<Option<Option<T>>, D::Error>
where
    D: serde::Deserializer<'de>,
    T: Deserialize<'de>,
{
    Option::<T>::deserialize(d).map(Some)
}

impl TryFrom<PartialEnvConfig> for EnvConfig {
    type Error = EnvError;

    fn try_from(p: PartialEnvConfig) -> Result<Self, EnvError> {
        let d = EnvConfig::from_mode(p.mode);
        let c = EnvConfig {
            mode: p.mode,
            frame_skip_min: p.frame_skip_min.unwrap_or(d.frame_skip_min),
            frame_skip_max: p.frame_skip_max.unwrap_or(d.frame_skip_max),
            sticky_prob: p.sticky_prob.unwrap_or(d.sticky_prob),
            max_pool_last_two: p.max_pool_last_two.unwrap_or(d.max_pool_last_two),
            noop_max: p.noop_max.unwrap_or(d.noop_max),
            max_episode_steps: p.max_episode_steps.unwrap_or(d.max_episode_steps),
            full_action_set: p.full_action_set.unwrap_or(d.full_action_set),
            rom: p.rom.unwrap_or(d.rom),
            contrast_rgb_sum: p.contrast_rgb_sum.unwrap_or(d.contrast_rgb_sum),
            downsample: p.downsample.unwrap_or(d.downsample),
            crop: p.crop.unwrap_or(d.crop),
            ale_verbose: p.ale_verbose.unwrap_or(d.ale_verbose),
        };
        c.validate()?;
        Ok(c)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn modes_have_their_documented_settings() {
        let v0 = EnvConfig::from_mode(EnvMode::V0);
        assert_eq!(
            (v0.frame_skip_min, v0.frame_skip_max, v0.sticky_prob),
            (2, 4, 0.25)
        );
        assert_eq!(v0.max_episode_steps, Some(10_000));
        let n = EnvConfig::from_mode(EnvMode::Nature);
        assert_eq!(
            (n.frame_skip_min, n.frame_skip_max, n.sticky_prob),
            (4, 4, 0.0)
        );
        assert!(n.max_pool_last_two && n.noop_max == 30);
        let v5 = EnvConfig::from_mode(EnvMode::V5);
        assert_eq!(
            (v5.frame_skip_min, v5.sticky_prob, v5.max_episode_steps),
            (4, 0.25, Some(27_000))
        );
    }

    #[test]
    fn validation_rejects_out_of_range_values() {
        let ok = EnvConfig::default();
        assert!(ok.validate().is_ok());
        for bad in [
            EnvConfig {
                frame_skip_min: 0,
                ..ok.clone()
            },
            EnvConfig {
                frame_skip_min: 5,
                frame_skip_max: 4,
                ..ok.clone()
            },
            EnvConfig {
                sticky_prob: 1.5,
                ..ok.clone()
            },
            EnvConfig {
                sticky_prob: -0.1,
                ..ok.clone()
            },
            EnvConfig {
                sticky_prob: f64::NAN,
                ..ok.clone()
            },
            EnvConfig {
                max_episode_steps: Some(0),
                ..ok.clone()
            },
        ] {
            assert!(
                matches!(bad.validate(), Err(EnvError::InvalidConfig(_))),
                "{bad:?}"
            );
        }
    }

    #[test]
    fn serde_fills_missing_fields_from_the_mode_and_validates() {
        let c: EnvConfig = serde_json::from_str(r#"{"mode":"nature","noop_max":0}"#).unwrap();
        assert_eq!(
            c,
            EnvConfig {
                noop_max: 0,
                ..EnvConfig::from_mode(EnvMode::Nature)
            }
        );
        let c: EnvConfig = serde_json::from_str(r#"{"max_episode_steps":null}"#).unwrap();
        assert_eq!(
            c,
            EnvConfig {
                max_episode_steps: None,
                ..EnvConfig::default()
            }
        );
        let full = EnvConfig::from_mode(EnvMode::V5);
        let back: EnvConfig = serde_json::from_str(&serde_json::to_string(&full).unwrap()).unwrap();
        assert_eq!(back, full);
        assert!(serde_json::from_str::<EnvConfig>(r#"{"frame_skip_min":0}"#).is_err());
        assert!(serde_json::from_str::<EnvConfig>(r#"{"mode":"v1"}"#).is_err());
    }

    /// The crop is read from a config file (the article's when missing, so earlier runs' files
    /// load unchanged), an unknown one is refused, and it enters the saved state's fingerprint
    /// only when it is not the article's, so earlier checkpoints' fingerprints still match.
    #[test]
    fn the_crop_is_read_refused_and_fingerprinted() {
        let c: EnvConfig = toml::from_str("mode = \"v5\"\ncrop = \"mothership\"").unwrap();
        assert_eq!(c.crop, Crop::Mothership);
        let d: EnvConfig = toml::from_str("mode = \"v5\"").unwrap();
        assert_eq!(d.crop, Crop::Article);
        let e = toml::from_str::<EnvConfig>("crop = \"tall\"").unwrap_err();
        assert!(e.to_string().contains("mothership"), "{e}");
        let back: EnvConfig = toml::from_str(&toml::to_string(&c).unwrap()).unwrap();
        assert_eq!(back, c);
        assert!(!d.dynamics_fingerprint().contains("crop"));
        assert!(c.dynamics_fingerprint().ends_with(" crop=Mothership"));
        assert_eq!(c.with_mode(EnvMode::Nature).crop, Crop::Mothership);
    }
}

//! `experiment ablation`: the `strong` preset (or `strong-v1`) with each of its components
//! switched off in turn.

use super::*;

/// One arm of the ablation: the `strong` preset with one component switched off.
pub struct Ablation {
    /// Its name (`--arms`, the run directory `NAME-seedS`).
    pub name: &'static str,
    /// What it switches off, and what takes its place.
    pub what: &'static str,
    /// The TOML keys that do it, over the preset and `--config`.
    pub keys: &'static str,
    /// Whether the arm's configuration really switches the component off against the preset's
    /// (`--config` may already have, or made it moot: the loss, say, under a quantile head).
    pub switches: fn(arm: &Config, preset: &Config) -> bool,
}

/// The ablation's arms; the first, with no keys, is the preset itself. The others are the
/// preset's on/off components and its replay size; its other settings (Adam's, the target
/// period, the batch, the update rate) are the published agents' or measured at full budget
/// (docs/strong.md), and not ablated.
/// The falling learning rate is left out too: its schedule starts at agent step 250 000 (1 M
/// frames) and has barely moved by the ablation's budget, so it is measured at full budget
/// instead (docs/strong.md).
pub const ABLATIONS: &[Ablation] = &[
    Ablation {
        name: "strong",
        what: "nothing (the preset)",
        keys: "",
        switches: |_, _| true,
    },
    Ablation {
        name: "no-dueling",
        what: "the dueling head (a plain dense head instead)",
        keys: "dueling = false",
        switches: |a, p| p.dueling && !a.dueling,
    },
    Ablation {
        name: "n-step-1",
        what: "3-step returns (1-step instead)",
        keys: "n_step = 1",
        switches: |a, p| p.n_step > 1 && a.n_step == 1,
    },
    Ablation {
        name: "no-double",
        what: "Double DQN (the target network's own max instead)",
        keys: "double_dqn = false",
        switches: |a, p| p.double_dqn && !a.double_dqn,
    },
    Ablation {
        name: "no-life-loss",
        what: "a lost life ending bootstrapping (only the game's end does)",
        keys: "life_loss_terminal = false",
        switches: |a, p| p.life_loss_terminal && !a.life_loss_terminal,
    },
    Ablation {
        name: "no-reward-clip",
        what: "reward clipping to ±1 (the game's rewards instead)",
        keys: "clip_rewards = false",
        switches: |a, p| p.clip_rewards && !a.clip_rewards,
    },
    Ablation {
        name: "mse",
        what: "the Huber loss (squared error instead)",
        keys: "loss = \"mse\"",
        switches: |a, p| p.loss == LossKind::Huber && a.loss == LossKind::Mse && p.quantiles == 0,
    },
    Ablation {
        name: "no-grad-clip",
        what: "clipping the gradient's norm to 10 (no clipping)",
        keys: "clip_grad_norm = 0.0",
        switches: |a, p| p.clip_grad_norm > 0.0 && a.clip_grad_norm == 0.0,
    },
    Ablation {
        name: "small-replay",
        what: "the preset's replay memory (100 000 transitions instead)",
        keys: "replay_capacity = 100000",
        switches: |a, p| a.replay_capacity < p.replay_capacity,
    },
    Ablation {
        name: "pick-pixels",
        what: "max-pooled downsampling (each 2x2 block's top-left pixel instead)",
        keys: "[env]\ndownsample = \"pick\"",
        switches: |a, p| {
            p.env.downsample == Downsample::Max && a.env.downsample == Downsample::Pick
        },
    },
];

#[derive(Debug, Args)]
pub struct AblationArgs {
    /// The preset the arms (and `--config`'s keys) start from: `strong`, or `strong-v1` (the
    /// first `strong`, whose ablation is docs/strong/ablation/).
    #[arg(long, default_value = "strong", value_parser = parse_strong_preset)]
    preset: Preset,
    /// The training seed of every arm (not 1 000 000, the seed the protocol plays on).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Emulator frames per run.
    #[arg(long, default_value_t = 1_500_000)]
    frames: u64,
    /// The arms to train, by name (default: all; `strong`, the preset, is always trained).
    #[arg(long, value_delimiter = ',',
          value_parser = PossibleValuesParser::new(ABLATIONS.iter().map(|a| a.name)))]
    arms: Vec<String>,
    /// Runs trained at once (default: the cores divided by `--threads`, at least one).
    #[arg(long, value_parser = parse_jobs)]
    jobs: Option<usize>,
    /// Kernel threads per run.
    #[arg(long, default_value_t = 1)]
    threads: usize,
    /// Protocol episodes per final network (at least 100).
    #[arg(long, default_value_t = 100)]
    eval_episodes: u32,
    /// A TOML file of overrides applied to every arm before its own switch.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Keep each finished run's record in DIR (`DIR/NAME-seedS/`: its scores and counters,
    /// `metrics.csv` and `config.toml`, small enough to commit), and take a run recorded there
    /// for the same configuration, budget and evaluation as finished, even where its run
    /// directory is gone (another machine).
    #[arg(long, value_name = "DIR")]
    keep: Option<PathBuf>,
    /// The experiment directory.
    #[arg(long, default_value = "runs/experiment-ablation")]
    out: PathBuf,
    #[command(flatten)]
    slurm: SlurmArgs,
}

/// `experiment ablation`: the preset and the arms of [`ABLATIONS`] that `--arms` names (all by
/// default), with one seed and budget, each evaluated by the protocol and set against the
/// preset.
pub(super) fn ablation(args: &AblationArgs) -> anyhow::Result<()> {
    if args.frames == 0 || args.threads == 0 {
        bail!("--frames and --threads must be at least 1");
    }
    if args.eval_episodes < PROTOCOL_EPISODES {
        bail!(
            "the evaluation protocol plays at least {PROTOCOL_EPISODES} episodes (--eval-episodes)"
        );
    }
    if args.seed == PROTOCOL_SEED {
        bail!("--seed {PROTOCOL_SEED} is the seed the protocol plays on; train with another");
    }
    let arms: Vec<&Ablation> = ABLATIONS
        .iter()
        .filter(|a| a.keys.is_empty() || args.arms.is_empty() || args.arms.contains(&a.name.into()))
        .collect();
    let text = read_overrides(args.config.as_deref())?;
    let overrides: toml::Table = text.parse().context("--config is not valid TOML")?;
    args.slurm.check()?;
    let keep = slurm::keep_dir(&args.slurm, args.keep.as_deref(), &args.out);
    let keep = keep.as_deref();
    let preset =
        super::super::config_errors::resolve_file(Some(args.preset), &text, args.config.as_deref())
            .context("configuration of the runs")?;
    Config {
        seed: args.seed,
        max_frames: args.frames,
        ..preset.clone()
    }
    .validate()
    .context("--seed or --frames")?;
    // Every arm's configuration, checked before anything is written or trained: each must
    // switch its component off against the preset (`--config` may already have).
    let mut texts = Vec::new();
    for arm in &arms {
        let mut table = overrides.clone();
        merge_toml(
            &mut table,
            arm.keys.parse().expect("ABLATIONS' keys are TOML"),
        );
        let arm_text = toml::to_string(&table)?;
        let config = Config::resolve(Some(args.preset), Some(&arm_text))
            .with_context(|| format!("configuration of {}", arm.name))?;
        if !(arm.switches)(&config, &preset) {
            bail!(
                "arm `{}` would not switch off {} against the preset with --config's keys",
                arm.name,
                arm.what
            );
        }
        check_reuse(
            &args.out.join(format!("{}-seed{}", arm.name, args.seed)),
            keep,
            args.preset,
            &arm_text,
            args.seed,
        )?;
        texts.push(arm_text);
    }
    make_keep(keep)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let mut jobs = Vec::new();
    for (arm, arm_text) in arms.iter().zip(texts) {
        let cfg = args.out.join(format!("{}.toml", arm.name));
        write_config(&cfg, &arm_text)?;
        jobs.push(Job {
            label: arm.name,
            preset: args.preset,
            seed: args.seed,
            cfg,
            dir: args.out.join(format!("{}-seed{}", arm.name, args.seed)),
            threads: args.threads,
        });
    }
    let workers = args
        .jobs
        .unwrap_or_else(|| worker_count(None) / args.threads)
        .max(1);
    say!(
        "{} runs of {} frames (seed {}), {} at a time, into {}",
        jobs.len(),
        args.frames,
        args.seed,
        workers,
        args.out.display()
    );
    let sweep = Sweep {
        kind: "ablation",
        out: &args.out,
        keep,
        budget: Budget::Frames(args.frames),
        evals: Evals {
            protocol: args.eval_episodes,
            own_game: None,
        },
    };
    let Some(finished) = slurm::run_jobs(&args.slurm, &sweep, &jobs, Some(workers))? else {
        return Ok(());
    };
    let scores: Vec<Scores> = finished.iter().map(|f| f.record.protocol).collect();
    let summaries = finished
        .iter()
        .map(summarize)
        .collect::<anyhow::Result<Vec<_>>>()?;
    // The preset is the first arm.
    let (base_return, base_score) = (summaries[0].last100, scores[0].mean);
    let mut rows = Vec::new();
    let mut groups = Vec::new();
    for (((job, arm), r), s) in jobs.iter().zip(&arms).zip(summaries).zip(&scores) {
        rows.push(format!(
            "| {} | {} | {} | {:.2} | {:.0} | {:.1} | {:+.1} | {} | {:+.1} |",
            job.label,
            arm.what,
            r.frames,
            r.hours,
            r.steps_per_second,
            r.last100,
            r.last100 - base_return,
            scores_cell(s),
            s.mean - base_score
        ));
        groups.push(Group {
            label: job.label.to_string(),
            seeds: vec![r.points],
        });
    }
    let title = format!(
        "Space Invaders, {} preset ablation: seed {}, {} frames",
        args.preset.name(),
        args.seed,
        args.frames
    );
    plot_groups_frames(&groups, &[], &title, 100, &args.out.join("rewards.png"))?;
    let name = args.preset.name();
    let table = format!(
        "# The {name} preset, each component switched off in turn\n\nCommand: `{}`\n\nBudget: {} frames per run, seed {}, {} thread(s) each, {} at a time. Evaluation: the protocol, {} episodes of `v5` with ε = {PROTOCOL_EPSILON} on seed {PROTOCOL_SEED}. Δ: against the preset (`{name}`).\n\n| arm | switched off | frames | wall hours | agent steps/s | training return, last 100 episodes | Δ | protocol score: mean ± std (min–max) | Δ |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n{}\n\nOne seed per arm: one network's protocol score moves by about ±50 from one checkpoint to the next, and seeds of one configuration differed by up to about 90 in training return at 1.5 M frames (docs/strong.md), so only larger differences say something. Figure: `rewards.png`.\n",
        command_line(),
        args.frames,
        args.seed,
        args.threads,
        workers,
        args.eval_episodes,
        rows.join("\n"),
    );
    std::fs::write(args.out.join("results.md"), &table).context("cannot write results.md")?;
    out!("{table}");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn leaves(c: &Config) -> Vec<(String, toml::Value)> {
        config_leaves(c).into_iter().collect()
    }

    /// Each arm over either bare preset (`--preset`) changes exactly the one setting its keys
    /// name, and its check says it switches that off; over an arm's own keys the check refuses it.
    #[test]
    fn every_arm_switches_off_one_setting_of_the_preset() {
        for p in [Preset::Strong, Preset::StrongV1] {
            arms_switch_off_one_setting_of(p);
        }
    }

    fn arms_switch_off_one_setting_of(p: Preset) {
        let preset = Config::preset(p);
        assert!(ABLATIONS[0].keys.is_empty() && ABLATIONS[0].name == "strong");
        for arm in &ABLATIONS[1..] {
            let config = Config::resolve(Some(p), Some(arm.keys)).unwrap();
            let changed: Vec<String> = leaves(&config)
                .into_iter()
                .zip(leaves(&preset))
                .filter(|(a, p)| a != p)
                .map(|(a, _)| a.0)
                .collect();
            let key = arm
                .keys
                .rsplit('\n')
                .next()
                .unwrap()
                .split(" = ")
                .next()
                .unwrap();
            assert_eq!(changed.len(), 1, "{}: {changed:?}", arm.name);
            assert!(changed[0].ends_with(key), "{}: {changed:?}", arm.name);
            assert!((arm.switches)(&config, &preset), "{}", arm.name);
            assert!(
                !(arm.switches)(&config, &config),
                "{}: already off",
                arm.name
            );
        }
        let names: Vec<&str> = ABLATIONS.iter().map(|a| a.name).collect();
        let mut unique = names.clone();
        unique.sort_unstable();
        unique.dedup();
        assert_eq!(unique.len(), names.len(), "{names:?}");
    }
}

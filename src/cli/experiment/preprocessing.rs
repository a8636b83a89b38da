//! `experiment preprocessing`: the article's comparison of inputs, vanilla against stacked and
//! composed, with the notebook's own curve.

use super::*;

#[derive(Debug, Args)]
pub struct PreprocessingArgs {
    /// Episodes per run (the article: 800).
    #[arg(long, default_value_t = 800)]
    episodes: u64,
    /// Seeds per configuration (0, 1, ...).
    #[arg(long, default_value_t = 1)]
    seeds: u64,
    /// Also train the `article` preset with these pipelines.
    #[arg(long = "pipeline", value_enum)]
    pipelines: Vec<Pipeline>,
    /// Runs trained at once (default: the number of cores).
    #[arg(long, value_parser = parse_jobs)]
    jobs: Option<usize>,
    /// Evaluation episodes per final checkpoint, with ε = 0.05 in the run's own game (each is
    /// also evaluated by the protocol: 100 episodes of `v5`).
    #[arg(long, default_value_t = 30)]
    eval_episodes: u32,
    /// A TOML file of overrides applied to every run (e.g. a shorter ε decay for a small budget).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// The article's notebook's own curve, digitised from its plot
    /// (`docs/experiment/notebook/plot-digitized.csv`), drawn as the band its 100-episode mean
    /// lies in.
    #[arg(long, value_name = "CSV")]
    notebook: Option<PathBuf>,
    /// Keep each finished run's record in DIR (`DIR/NAME-seedS/`: its scores and counters,
    /// `metrics.csv` and `config.toml`, small enough to commit), and take a run recorded there
    /// for the same configuration, budget and evaluation as finished, even where its run
    /// directory is gone (another machine).
    #[arg(long, value_name = "DIR")]
    keep: Option<PathBuf>,
    /// The experiment directory.
    #[arg(long, default_value = "runs/experiment-preprocessing")]
    out: PathBuf,
    #[command(flatten)]
    slurm: SlurmArgs,
}

/// One configuration of the comparison.
pub(super) struct Arm {
    label: String,
    preset: Preset,
    pipeline: Option<Pipeline>,
}

pub(super) fn arms(args: &PreprocessingArgs) -> Vec<Arm> {
    let mut arms: Vec<Arm> = [
        Preset::ArticleVanilla,
        Preset::Article,
        Preset::ArticleAsWritten,
    ]
    .into_iter()
    .map(|p| Arm {
        label: p.name().to_string(),
        preset: p,
        pipeline: None,
    })
    .collect();
    for &p in &args.pipelines {
        let name = p.to_possible_value().expect("named").get_name().to_string();
        arms.push(Arm {
            label: format!("article+{name}"),
            preset: Preset::Article,
            pipeline: Some(p),
        });
    }
    arms
}

pub(super) fn preprocessing(args: &PreprocessingArgs) -> anyhow::Result<()> {
    if args.episodes == 0 || args.seeds == 0 || args.eval_episodes == 0 {
        bail!("--episodes, --seeds and --eval-episodes must be at least 1");
    }
    let overrides = read_overrides(args.config.as_deref())?;
    // Read before hours of training, so a bad file fails now.
    let notebook = match &args.notebook {
        Some(p) => vec![read_digitized(
            p,
            "the article's notebook (stacked, running max), digitised: its mean lies in the band",
        )?],
        None => Vec::new(),
    };
    args.slurm.check()?;
    let keep = slurm::keep_dir(&args.slurm, args.keep.as_deref(), &args.out);
    let keep = keep.as_deref();
    let arms = arms(args);
    // Every run's configuration, checked before anything is written or starts (and each run
    // already in --out against it).
    let mut jobs = Vec::new();
    let mut arm_texts = Vec::new();
    for arm in &arms {
        let mut table: toml::Table = overrides.parse().context("--config is not valid TOML")?;
        if let Some(p) = arm.pipeline {
            table.insert("pipeline".into(), toml::Value::try_from(p)?);
        }
        let text = toml::to_string(&table)?;
        Config::resolve(Some(arm.preset), Some(&text))
            .map_err(|e| {
                let file = args.config.as_deref().unwrap_or(Path::new(""));
                super::super::config_errors::locate(e, &overrides, file)
            })
            .with_context(|| format!("configuration of {}", arm.label))?;
        for seed in 0..args.seeds {
            let dir = args.out.join(format!("{}-seed{seed}", arm.label));
            check_reuse(&dir, keep, arm.preset, &text, seed)?;
        }
        arm_texts.push(text);
    }
    // Only now is anything made: a bad configuration leaves no folder behind.
    make_keep(keep)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    for (arm, text) in arms.iter().zip(arm_texts) {
        let cfg_path = args.out.join(format!("{}.toml", arm.label));
        write_config(&cfg_path, &text)?;
        for seed in 0..args.seeds {
            jobs.push(Job {
                label: &arm.label,
                preset: arm.preset,
                seed,
                cfg: cfg_path.clone(),
                dir: args.out.join(format!("{}-seed{seed}", arm.label)),
                threads: 1,
            });
        }
    }
    say!(
        "{} runs of {} episodes, into {}",
        jobs.len(),
        args.episodes,
        args.out.display()
    );
    // Every final checkpoint is evaluated both ways as soon as it has trained.
    let evals = Evals {
        protocol: PROTOCOL_EPISODES,
        own_game: Some(args.eval_episodes),
    };
    let sweep = Sweep {
        kind: "preprocessing",
        out: &args.out,
        keep,
        budget: Budget::Episodes(args.episodes),
        evals,
    };
    let Some(finished) = slurm::run_jobs(&args.slurm, &sweep, &jobs, args.jobs)? else {
        return Ok(());
    };
    let mut finished = finished.into_iter();
    let (mut rows, mut run_rows, mut stretch_rows) = (Vec::new(), Vec::new(), Vec::new());
    let mut groups = Vec::new();
    let stretches = (args.episodes as usize).div_ceil(STRETCH);
    for arm in &arms {
        let (mut last100, mut evals, mut seeds) = (Vec::new(), Vec::new(), Vec::new());
        let mut protocol = Vec::new();
        for seed in 0..args.seeds {
            let run = finished.next().expect("a run per seed, in the jobs' order");
            // Up to the episodes it was evaluated at (its directory may have trained on since).
            let mut points = read_metrics(&run.metrics)?;
            points.retain(|p| p.0 <= run.record.counters.episodes as f64);
            let tail = &points[points.len().saturating_sub(100)..];
            last100.push(tail.iter().map(|p| p.1).sum::<f64>() / tail.len().max(1) as f64);
            let own = run.record.own_game.expect("evaluated in its own game");
            evals.push(own.mean);
            protocol.push(run.record.protocol.mean);
            let c = run.record.counters;
            run_rows.push(format!(
                "| {} | {seed} | {} | {} | {:.2} | {:.1} | {} | {} |",
                arm.label,
                c.agent_steps,
                c.frames,
                c.wall_seconds / 3600.0,
                last100[last100.len() - 1],
                scores_cell(&own),
                scores_cell(&run.record.protocol)
            ));
            seeds.push(points);
        }
        rows.push(format!(
            "| {} | {} | {} | {} | {} |",
            arm.label,
            args.seeds,
            mean_std(&last100),
            mean_std(&evals),
            mean_std(&protocol)
        ));
        // Each stretch's mean reward per seed, then its mean and range over the seeds.
        let cells: Vec<String> = (0..stretches)
            .map(|k| {
                let per_seed: Vec<f64> = seeds
                    .iter()
                    .filter_map(|pts| {
                        let s = pts.get(k * STRETCH..pts.len().min((k + 1) * STRETCH))?;
                        (!s.is_empty()).then(|| s.iter().map(|p| p.1).sum::<f64>() / s.len() as f64)
                    })
                    .collect();
                range_cell(&per_seed)
            })
            .collect();
        stretch_rows.push(format!("| {} | {} |", arm.label, cells.join(" | ")));
        groups.push(Group {
            label: arm.label.clone(),
            seeds,
        });
    }
    let stretch_head: Vec<String> = (0..stretches)
        .map(|k| {
            let last = ((k + 1) * STRETCH).min(args.episodes as usize);
            format!("{}–{last}", k * STRETCH + 1)
        })
        .collect();
    let png = args.out.join("rewards.png");
    let title = format!(
        "Space Invaders: {} episodes, {} seed(s) per configuration",
        args.episodes, args.seeds
    );
    plot_groups(&groups, &notebook, &title, 100, &png)?;
    let table = format!(
        "# Preprocessing experiment\n\nCommand: `{}`\n\nBudget: {} episodes per run, {} seed(s) per configuration; evaluation over {} episodes with ε = 0.05 in the run's own game (the article's: `v0`), and by the evaluation protocol ({PROTOCOL_EPISODES} episodes of `v5`, ε = {PROTOCOL_EPSILON}, seed {PROTOCOL_SEED}).\n\n| configuration | seeds | mean reward, last 100 episodes | evaluation score | protocol score |\n| --- | --- | --- | --- | --- |\n{}\n\nMeans over seeds ± their standard deviation (population). Figure: `rewards.png`.\n\nTraining reward by stretch of {STRETCH} episodes: the mean over seeds of each run's mean episode reward in the stretch (lowest–highest seed).\n\n| configuration | {} |\n| --- |{}\n{}\n\nEvery run: its final network's evaluation in its own game (seed 1000 + the run's seed) and by the protocol, each `mean ± std (min–max)` over its episodes.\n\n| configuration | seed | agent steps | frames | wall hours | mean reward, last 100 episodes | evaluation | protocol |\n| --- | --- | --- | --- | --- | --- | --- | --- |\n{}\n",
        command_line(),
        args.episodes,
        args.seeds,
        args.eval_episodes,
        rows.join("\n"),
        stretch_head.join(" | "),
        " --- |".repeat(stretches),
        stretch_rows.join("\n"),
        run_rows.join("\n")
    );
    std::fs::write(args.out.join("results.md"), &table).context("cannot write results.md")?;
    out!("{table}");
    Ok(())
}

/// Episodes per stretch in the preprocessing table of training reward by stretch.
pub(super) const STRETCH: usize = 100;

//! `experiment strong`: the `strong` preset (or `strong-v1`, or any overrides of either) over
//! training seeds 1..=N, each evaluated by the protocol.

use super::*;

#[derive(Debug, Args)]
pub struct StrongArgs {
    /// The preset the runs (and `--config`'s keys) start from: `strong`, or `strong-v1`, the
    /// first `strong`, whose published results (docs/strong.md) reproduce under that name.
    #[arg(long, default_value = "strong", value_parser = parse_strong_preset)]
    preset: Preset,
    /// Training seeds 1, 2, … (the protocol plays on seed 1 000 000).
    #[arg(long, default_value_t = 3)]
    seeds: u64,
    /// Emulator frames per run (default: the preset's, 40 million for `strong`, 13.5 million for
    /// `strong-v1`).
    #[arg(long)]
    frames: Option<u64>,
    /// Runs trained at once (default: the cores divided by `--threads`, at least one).
    #[arg(long, value_parser = parse_jobs)]
    jobs: Option<usize>,
    /// Kernel threads per run: 2 for one run alone on a 2-core machine (`strong-v1`'s 13.5
    /// million frames took 2.25–2.32 hours so on an AVX512-BF16 host), 1 for runs side by side.
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Protocol episodes per final network (at least 100).
    #[arg(long, default_value_t = 100)]
    eval_episodes: u32,
    /// A TOML file of overrides applied to every run (e.g. `precision = "bf16"`).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Published curves to draw beside the runs', from a CSV `agent,frames,score` (e.g.
    /// docs/strong/dopamine-spaceinvaders.csv).
    #[arg(long, value_name = "CSV")]
    reference: Option<PathBuf>,
    /// The reference agents to draw (default: all in the file).
    #[arg(long, value_delimiter = ',')]
    agents: Vec<String>,
    /// Keep each finished run's record in DIR (`DIR/NAME-seedS/`: its scores and counters,
    /// `metrics.csv` and `config.toml`, small enough to commit), and take a run recorded there
    /// for the same configuration, budget and evaluation as finished, even where its run
    /// directory is gone (another machine).
    #[arg(long, value_name = "DIR")]
    keep: Option<PathBuf>,
    /// The experiment directory.
    #[arg(long, default_value = "runs/experiment-strong")]
    out: PathBuf,
    #[command(flatten)]
    slurm: SlurmArgs,
}

/// `experiment strong`: the preset with seeds 1..=N, each evaluated by the protocol.
pub(super) fn strong(args: &StrongArgs) -> anyhow::Result<()> {
    let preset = args.preset;
    let frames = args
        .frames
        .unwrap_or_else(|| Config::preset(preset).max_frames);
    if args.seeds == 0 || frames == 0 || args.threads == 0 {
        bail!("--seeds, --frames and --threads must be at least 1");
    }
    if args.eval_episodes < PROTOCOL_EPISODES {
        bail!(
            "the evaluation protocol plays at least {PROTOCOL_EPISODES} episodes (--eval-episodes)"
        );
    }
    let text = read_overrides(args.config.as_deref())?;
    let config =
        super::super::config_errors::resolve_file(Some(preset), &text, args.config.as_deref())
            .context("configuration of the runs")?;
    Config {
        seed: args.seeds,
        max_frames: frames,
        ..config
    }
    .validate()
    .context("--seeds or --frames")?;
    // The references are read before hours of training, so a bad file fails now.
    let references = match &args.reference {
        Some(r) => read_references(r, &args.agents)?,
        None => Vec::new(),
    };
    args.slurm.check()?;
    let keep = slurm::keep_dir(&args.slurm, args.keep.as_deref(), &args.out);
    let keep = keep.as_deref();
    make_keep(keep)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    for seed in 1..=args.seeds {
        check_reuse(
            &args.out.join(format!("strong-seed{seed}")),
            keep,
            preset,
            &text,
            seed,
        )?;
    }
    let cfg = args.out.join("strong.toml");
    write_config(&cfg, &text)?;
    let jobs: Vec<Job<'_>> = (1..=args.seeds)
        .map(|seed| Job {
            label: "strong",
            preset,
            seed,
            cfg: cfg.clone(),
            dir: args.out.join(format!("strong-seed{seed}")),
            threads: args.threads,
        })
        .collect();
    say!(
        "{} runs of {} frames, into {}",
        jobs.len(),
        frames,
        args.out.display()
    );
    // Runs at once: as many as the cores hold at `--threads` each, unless `--jobs` says.
    let workers = args
        .jobs
        .unwrap_or_else(|| worker_count(None) / args.threads)
        .max(1);
    let sweep = Sweep {
        kind: "strong",
        out: &args.out,
        keep,
        budget: Budget::Frames(frames),
        evals: Evals {
            protocol: args.eval_episodes,
            own_game: None,
        },
    };
    let Some(finished) = slurm::run_jobs(&args.slurm, &sweep, &jobs, Some(workers))? else {
        return Ok(());
    };
    let (mut rows, mut means, mut seeds) = (Vec::new(), Vec::new(), Vec::new());
    for (job, run) in jobs.iter().zip(&finished) {
        let (r, s) = (summarize(run)?, run.record.protocol);
        rows.push(format!(
            "| {} | {} | {:.2} | {:.0} | {:.1} | {} |",
            job.seed,
            r.frames,
            r.hours,
            r.steps_per_second,
            r.last100,
            scores_cell(&s)
        ));
        means.push(s.mean);
        seeds.push(r.points);
    }
    let groups = [Group {
        label: preset.name().to_string(),
        seeds,
    }];
    // What the runs are: the preset, or the preset with the keys of `--config`.
    let what = match &args.config {
        Some(path) => format!("{} preset with {}", preset.name(), path.display()),
        None => format!("{} preset", preset.name()),
    };
    let title = format!("Space Invaders, {what}: {} seed(s)", args.seeds);
    plot_groups_frames(
        &groups,
        &references,
        &title,
        100,
        &args.out.join("rewards.png"),
    )?;
    let table = format!(
        "# The {what} over {} seeds\n\nCommand: `{}`\n\nBudget: {} frames per run, {} thread(s) each, {} at a time. Evaluation: the protocol, {} episodes of `v5` with ε = {PROTOCOL_EPSILON} on seed {PROTOCOL_SEED}.\n\n| seed | frames | wall hours | agent steps/s | training return, last 100 episodes | protocol score: mean ± std (min–max) |\n| --- | --- | --- | --- | --- | --- |\n{}\n\nMean protocol score over the seeds: {}. Figure: `rewards.png`.\n",
        args.seeds,
        command_line(),
        frames,
        args.threads,
        workers,
        args.eval_episodes,
        rows.join("\n"),
        mean_std(&means)
    );
    std::fs::write(args.out.join("results.md"), &table).context("cannot write results.md")?;
    out!("{table}");
    Ok(())
}

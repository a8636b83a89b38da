//! `invaders eval`: play whole episodes and summarise their scores.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use clap::{Args, ValueEnum};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use invaders::dqn::checkpoint;
use invaders::dqn::play_evaluation_episode;
use invaders::dqn::Preset;
use invaders::env::{mothership_on_screen, EnvConfig, EnvMode, Observer, SpaceInvaders};
use invaders::tensor::Tensor;

// The emulator's screen size (the ALE's).
use invaders::env::ale::{SCREEN_HEIGHT as SCREEN_H, SCREEN_WIDTH as SCREEN_W};

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Play uniformly random actions (the baseline every agent must beat).
    #[arg(long)]
    random: bool,
    /// A checkpoint to evaluate (`RUN_DIR/checkpoint.safetensors`, or the run directory), or a
    /// model (a model file, or a shipped model's folder such as models/strong).
    #[arg(long, value_name = "PATH", conflicts_with = "random")]
    checkpoint: Option<PathBuf>,
    /// Refuse a checkpoint trained with another preset (its network's input shape differs for
    /// `article-vanilla`).
    #[arg(long, value_enum, requires = "checkpoint")]
    preset: Option<Preset>,
    /// The evaluation protocol the `strong` preset is judged by (README, "Evaluation"): the `v5`
    /// game (4 frames per step, sticky actions 0.25, 27 000-step cap), ε = 0.01, 100 episodes
    /// (or more with --episodes), and an evaluation seed (default 1000000) that must differ from
    /// the training seed.
    #[arg(long, conflicts_with_all = ["mode", "epsilon"])]
    protocol: bool,
    /// Exploration rate while evaluating a checkpoint [default: 0.05].
    #[arg(long)]
    epsilon: Option<f32>,
    /// Record the first episode as an animated GIF at the emulator's full 210x160 colour. An
    /// existing file is refused unless --force, and replaced atomically; the checkpoint itself,
    /// never. A symbolic link's target is written, a character device or FIFO written through
    /// (docs/runs.md, "Output files").
    #[arg(long, value_name = "FILE")]
    gif: Option<PathBuf>,
    /// Replace an existing --gif file.
    #[arg(long, requires = "gif")]
    force: bool,
    /// Worker threads for the kernels (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// The products' arithmetic while acting (default: the checkpoint's).
    #[arg(long, value_enum, requires = "checkpoint")]
    precision: Option<invaders::ops::plan::Precision>,
    /// Number of episodes [default: 30; 100 with --protocol].
    #[arg(long)]
    episodes: Option<u32>,
    /// Seed of the environment (the agent's random choices use a stream derived from it)
    /// [default: 0; 1000000 with --protocol].
    #[arg(long)]
    seed: Option<u64>,
    /// Environment mode (default: v0 for --random, the run's own for --checkpoint).
    #[arg(long, value_enum)]
    mode: Option<EnvMode>,
    /// Space Invaders ROM to use instead of the bundled one.
    #[arg(long, value_name = "PATH")]
    rom: Option<PathBuf>,
}

/// The evaluation protocol's exploration rate, episodes and default seed.
pub(super) const PROTOCOL_EPSILON: f32 = 0.01;
pub(super) const PROTOCOL_EPISODES: u32 = 100;
pub(super) const PROTOCOL_SEED: u64 = 1_000_000;

/// What to play: the arguments with the protocol's or the defaults' values filled in.
struct Plan {
    epsilon: f32,
    episodes: u32,
    seed: u64,
    mode: Option<EnvMode>,
}

pub fn run(args: &EvalArgs) -> anyhow::Result<()> {
    super::in_pool(args.threads, || eval(args))
}

fn plan(args: &EvalArgs) -> anyhow::Result<Plan> {
    let plan = if args.protocol {
        let episodes = args.episodes.unwrap_or(PROTOCOL_EPISODES);
        if episodes < PROTOCOL_EPISODES {
            bail!("the evaluation protocol plays at least {PROTOCOL_EPISODES} episodes");
        }
        Plan {
            epsilon: PROTOCOL_EPSILON,
            episodes,
            seed: args.seed.unwrap_or(PROTOCOL_SEED),
            mode: Some(EnvMode::V5),
        }
    } else {
        Plan {
            epsilon: args.epsilon.unwrap_or(0.05),
            episodes: args.episodes.unwrap_or(30),
            seed: args.seed.unwrap_or(0),
            mode: args.mode,
        }
    };
    if plan.episodes == 0 {
        bail!("--episodes must be at least 1");
    }
    if !(0.0..=1.0).contains(&plan.epsilon) {
        bail!("--epsilon must be in [0, 1], got {}", plan.epsilon);
    }
    Ok(plan)
}

fn eval(args: &EvalArgs) -> anyhow::Result<()> {
    let plan = plan(args)?;
    if let Some(path) = &args.checkpoint {
        return run_checkpoint(args, &plan, path);
    }
    if !args.random {
        bail!("eval needs --checkpoint PATH or --random");
    }
    if args.gif.is_some() {
        bail!("--gif records a checkpoint's play; use it with --checkpoint");
    }
    let mode = plan.mode.unwrap_or(EnvMode::V0);
    let config = EnvConfig {
        rom: args.rom.clone(),
        ..EnvConfig::from_mode(mode)
    };
    let mut env = SpaceInvaders::new(&config, plan.seed).context("cannot start Space Invaders")?;
    let mut agent = ChaCha8Rng::seed_from_u64(plan.seed);
    agent.set_stream(1); // independent of the environment's stream 0
    let n = env.n_actions();
    let mut scores = Vec::with_capacity(plan.episodes as usize);
    let mut endings = [0u64; 3];
    for episode in 0..plan.episodes {
        if episode > 0 {
            env.reset();
        }
        let mut lives = Lives::default();
        lives.observe(env.lives());
        loop {
            let r = env.step(agent.random_range(0..n));
            lives.observe(r.lives);
            if r.terminal || r.truncated {
                break;
            }
        }
        let stats = env.episode();
        let ending = lives.ending(u64::from(stats.steps), config.max_episode_steps);
        out!(
            "episode {:>3}: score {:>6} steps {:>5} frames {:>6} lives {} -> {}: {}",
            episode + 1,
            stats.score,
            stats.steps,
            stats.frames,
            lives.before_last,
            lives.last,
            ending.describe()
        );
        endings[ending as usize] += 1;
        scores.push(stats.score);
        if super::streams::stdout_lost() {
            break;
        }
    }
    let s = Summary::of(&scores);
    out!(
        "random agent, mode {}, {} episodes, seed {}, games ended {}: {s}",
        mode.to_possible_value()
            .expect("modes are named")
            .get_name(),
        s.n,
        plan.seed,
        describe_endings(&endings),
    );
    Ok(())
}

/// Plays the planned episodes with the online network of a checkpoint or model file, ε-greedy.
fn run_checkpoint(args: &EvalArgs, plan: &Plan, path: &Path) -> anyhow::Result<()> {
    let file = checkpoint::network_file(path)?;
    let gif_out = match &args.gif {
        Some(gif) => Some(super::guard::OutputFile::check(
            gif,
            args.force,
            &[&file, path],
            "--gif",
        )?),
        None => None,
    };
    let model = checkpoint::load_model(&file)?;
    if let Some(p) = args.preset {
        if model.config.preset != p {
            bail!(
                "{} was trained with preset `{}`, not `{}`",
                file.display(),
                model.config.preset.name(),
                p.name()
            );
        }
    }
    if args.protocol && plan.seed == model.config.seed {
        bail!(
            "the evaluation protocol needs a seed other than the training seed ({}); pass another --seed",
            plan.seed
        );
    }
    let config = model.config;
    let mut env_config = config.env.clone();
    if let Some(mode) = plan.mode {
        // The game's dynamics change; the preprocessing the network was trained on does not.
        env_config = env_config.for_evaluation(mode);
    }
    if args.rom.is_some() {
        env_config.rom = args.rom.clone();
    }
    let mut env =
        SpaceInvaders::new(&env_config, plan.seed).context("cannot start Space Invaders")?;
    if env.n_actions() != model.n_actions {
        bail!(
            "the checkpoint has {} actions but the game has {}",
            model.n_actions,
            env.n_actions()
        );
    }
    let mut net = model.online;
    let head = invaders::dqn::Head::of(&config);
    let precision = args.precision.unwrap_or(config.precision);
    super::note_precision(precision);
    net.set_precision(precision);
    let mut observer = Observer::new(config.pipeline);
    let table = config.normalization.table();
    let [h, w, c] = config.input_shape();
    let mut input = Tensor::zeros(&[1, h, w, c]);
    let mut rng = ChaCha8Rng::seed_from_u64(plan.seed);
    rng.set_stream(1);
    let mut gif = match &gif_out {
        Some(out) => Some(GifRecorder::create(out)?),
        None => None,
    };
    let mut scores = Vec::with_capacity(plan.episodes as usize);
    let mut ships = Mothership::default();
    let mut endings = [0u64; 3];
    for episode in 0..plan.episodes {
        let mut recorder = if episode == 0 { gif.as_mut() } else { None };
        let mut record_error = None;
        let mut ship = Mothership::default();
        let mut lives = Lives::default();
        let (score, steps) = play_evaluation_episode(
            &mut env,
            &mut net,
            &head,
            &mut observer,
            &table,
            &mut input,
            plan.epsilon,
            &mut rng,
            |g| {
                ship.observe(mothership_on_screen(g.screen_rgb()), g.episode().score);
                lives.observe(g.lives());
                if let (Some(r), None) = (recorder.as_deref_mut(), &record_error) {
                    if let Err(e) = r.frame(g.screen_rgb()) {
                        record_error = Some(e);
                    }
                }
            },
        );
        if let Some(e) = record_error {
            return Err(e);
        }
        let ending = lives.ending(steps, env_config.max_episode_steps);
        out!(
            "episode {:>3}: score {score:>6} steps {steps:>5} mothership {}/{} lives {} -> {}: {}",
            episode + 1,
            ship.hits,
            ship.passes,
            lives.before_last,
            lives.last,
            ending.describe()
        );
        endings[ending as usize] += 1;
        ships.passes += ship.passes;
        ships.hits += ship.hits;
        scores.push(score);
        if super::streams::stdout_lost() {
            // Nobody reads the scores any more: stop playing (the GIF, if any, is complete).
            break;
        }
    }
    if let (Some(g), Some(p)) = (gif, &args.gif) {
        g.finish()?;
        out!("recorded episode 1 to {}", p.display());
    }
    let s = Summary::of(&scores);
    out!(
        "checkpoint {} (preset {}, {} episodes, {} frames trained), mode {}{}, epsilon {}, {} episodes, seed {}, mothership hit in {} of {} passes, games ended {}: {s}",
        file.display(),
        config.preset.name(),
        model.counters.episodes,
        model.counters.frames,
        env_config.mode.to_possible_value().expect("modes are named").get_name(),
        if args.protocol { " (the evaluation protocol)" } else { "" },
        plan.epsilon,
        s.n,
        plan.seed,
        ships.hits,
        ships.passes,
        describe_endings(&endings),
    );
    Ok(())
}

/// The mothership's passes over an episode and the agent's hits on it: a pass begins on a step
/// whose screen shows the ship after at least [`Mothership::GAP`] steps without it (the ship is
/// on screen for about 150 steps of 4 frames a pass), and a hit is a step that scores 200 or more
/// (the ship is worth 200, an alien 5 to 30).
#[derive(Default)]
struct Mothership {
    passes: u64,
    hits: u64,
    /// Steps since the ship was last on screen (`None` before it first was).
    off: Option<u64>,
    last_score: f64,
}

impl Mothership {
    const GAP: u64 = 8;

    /// One step: whether the ship is on screen, and the episode's score after the step.
    fn observe(&mut self, on_screen: bool, score: f64) {
        if on_screen {
            if self.off.is_none_or(|n| n >= Self::GAP) {
                self.passes += 1;
            }
            self.off = Some(0);
        } else if let Some(n) = &mut self.off {
            *n += 1;
        }
        if score >= self.last_score + 200.0 {
            self.hits += 1;
        }
        self.last_score = score;
    }
}

/// Writes an animated GIF frame by frame into its output file's temporary path, put in place at
/// the end ([`super::guard::Pending`]: a recorder dropped before [`GifRecorder::finish`], on an
/// error, leaves no temporary file and the old file as it was).
struct GifRecorder<'a> {
    encoder: gif::Encoder<std::io::BufWriter<std::fs::File>>,
    pending: super::guard::Pending<'a>,
}

impl<'a> GifRecorder<'a> {
    fn create(out: &'a super::guard::OutputFile) -> anyhow::Result<Self> {
        let pending = out.pending()?;
        let tmp = pending.path();
        let file = std::fs::File::create(tmp)
            .with_context(|| format!("cannot create {}", tmp.display()))?;
        let mut encoder = gif::Encoder::new(
            std::io::BufWriter::new(file),
            SCREEN_W as u16,
            SCREEN_H as u16,
            &[],
        )?;
        encoder.set_repeat(gif::Repeat::Infinite)?;
        Ok(GifRecorder { encoder, pending })
    }

    /// Appends one 210x160 RGB screen, shown for 1/20 s (an agent step is 2 to 4 frames at 60 Hz).
    fn frame(&mut self, rgb: &[u8]) -> anyhow::Result<()> {
        let mut frame = gif::Frame::from_rgb_speed(SCREEN_W as u16, SCREEN_H as u16, rgb, 10);
        frame.delay = 5;
        self.encoder
            .write_frame(&frame)
            .context("cannot write the GIF")
    }

    fn finish(self) -> anyhow::Result<()> {
        let mut w = self.encoder.into_inner().context("cannot finish the GIF")?;
        std::io::Write::flush(&mut w).context("cannot finish the GIF")?;
        drop(w);
        self.pending.commit()
    }
}

/// Mean, population standard deviation, min and max of episode scores.
struct Summary {
    n: usize,
    mean: f64,
    std: f64,
    min: f64,
    max: f64,
}

/// `mean M std S min A max B`, the line's ending that `experiment` reads the score from.
impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "mean {:.1} std {:.1} min {} max {}",
            self.mean, self.std, self.min, self.max
        )
    }
}

/// How a game ended: the last life lost to a bomb, the invaders landing (which ends the game
/// with lives to spare: the score stops wherever the wave was), or the step limit.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Ending {
    LastLife = 0,
    Landing = 1,
    StepLimit = 2,
}

impl Ending {
    fn describe(self) -> &'static str {
        match self {
            Ending::LastLife => "last life",
            Ending::Landing => "landing",
            Ending::StepLimit => "step limit",
        }
    }
}

/// The summary's count of each [`Ending`], indexed by it.
fn describe_endings(endings: &[u64; 3]) -> String {
    format!(
        "by the last life {}, by a landing {}, by the step limit {}",
        endings[Ending::LastLife as usize],
        endings[Ending::Landing as usize],
        endings[Ending::StepLimit as usize]
    )
}

/// The lives counter over an episode: its value after the last step and before it. A bomb
/// takes one life a step, so a game that ends with lives left, or that loses more than one in
/// its last step, ended by a landing. (A landing with one life left cannot be told from a bomb:
/// it counts as the last life.)
#[derive(Default)]
struct Lives {
    before_last: i32,
    last: i32,
}

impl Lives {
    /// One step (and the reset before the first): the lives shown after it.
    fn observe(&mut self, lives: i32) {
        self.before_last = self.last;
        self.last = lives;
    }

    /// The episode's end after `steps` agent steps under the game's step limit.
    fn ending(&self, steps: u64, limit: Option<u32>) -> Ending {
        if limit.is_some_and(|l| steps >= u64::from(l)) && self.last > 0 {
            Ending::StepLimit
        } else if self.last > 0 || self.before_last - self.last > 1 {
            Ending::Landing
        } else {
            Ending::LastLife
        }
    }
}

impl Summary {
    fn of(xs: &[f64]) -> Summary {
        let n = xs.len();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n as f64;
        Summary {
            n,
            mean,
            std: var.sqrt(),
            min: xs.iter().copied().fold(f64::INFINITY, f64::min),
            max: xs.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Summary;

    /// Passes are counted at the ship's arrival, not once per step or per flicker shorter than
    /// the gap; a hit is a 200-point step, not several aliens' points over several steps.
    #[test]
    fn mothership_passes_and_hits() {
        let mut m = super::Mothership::default();
        let seen = [0, 1, 1, 0, 0, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0];
        let score = [
            0, 0, 30, 30, 230, 230, 260, 290, 290, 320, 320, 320, 320, 320, 320, 320, 320, 545,
        ];
        for (&on, &s) in seen.iter().zip(&score) {
            m.observe(on == 1, s as f64);
        }
        assert_eq!((m.passes, m.hits), (2, 2));
    }

    /// A bomb takes one life a step; a game over with lives left, or with two or more lost in
    /// one step, is a landing; a game still alive at the step limit was cut.
    #[test]
    fn endings_follow_the_lives_counter() {
        use super::{Ending, Lives};
        let end = |lives: &[i32], steps: u64| {
            let mut l = Lives::default();
            for &n in lives {
                l.observe(n);
            }
            l.ending(steps, Some(100))
        };
        assert_eq!(end(&[3, 3, 2, 2, 1, 1, 0], 7), Ending::LastLife);
        assert_eq!(end(&[3, 3, 2, 2, 2], 5), Ending::Landing);
        assert_eq!(end(&[3, 3, 2, 2, 0], 5), Ending::Landing);
        assert_eq!(end(&[3, 3, 2, 2, 2], 100), Ending::StepLimit);
        assert_eq!(end(&[3, 2, 1, 0], 100), Ending::LastLife);
    }

    #[test]
    fn summary_uses_population_std() {
        let s = Summary::of(&[1.0, 3.0]);
        assert_eq!((s.mean, s.std, s.min, s.max), (2.0, 1.0, 1.0, 3.0));
    }
}

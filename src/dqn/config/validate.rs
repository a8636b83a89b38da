//! The range of every value: each numeric knob has a bound a real run could use.

use super::*;

impl Config {
    /// Checks every value's range: each numeric knob has a bound a real run could use, so an
    /// absurd value is a clear error, not an allocation failure, a hang or a value `config.toml`
    /// cannot hold (TOML integers are i64).
    pub fn validate(&self) -> anyhow::Result<()> {
        let c = self;
        if c.episodes == 0 {
            bail!("episodes must be at least 1");
        }
        for (name, v) in [
            ("episodes", c.episodes),
            ("max_frames", c.max_frames),
            ("seed", c.seed),
        ] {
            if v > NO_EPISODE_LIMIT {
                bail!("{name} must be at most {NO_EPISODE_LIMIT} (2^63 - 1), got {v}");
            }
        }
        for (name, v) in [
            ("train_every", c.train_every),
            ("learning_starts", c.learning_starts),
            ("target_update", c.target_update),
            ("epsilon_decay_steps", c.epsilon_decay_steps),
            ("checkpoint_every", c.checkpoint_every),
            ("plot_every", c.plot_every),
        ] {
            if v > MAX_STEPS_KNOB {
                bail!("{name} must be at most {MAX_STEPS_KNOB}, got {v}");
            }
        }
        if c.clip_grad_norm > 1e9 {
            bail!(
                "clip_grad_norm must be at most 1e9, got {}",
                c.clip_grad_norm
            );
        }
        if c.replay_capacity < c.batch_size + 8 {
            bail!(
                "replay_capacity ({}) must exceed batch_size + 8",
                c.replay_capacity
            );
        }
        if c.batch_size == 0 {
            bail!("batch_size must be at least 1");
        }
        // Upper bounds keep an absurd value a clear error instead of an allocation failure.
        if c.replay_capacity > MAX_REPLAY {
            bail!(
                "replay_capacity ({}) must be at most {MAX_REPLAY} (7 KB each)",
                c.replay_capacity
            );
        }
        if c.batch_size > MAX_BATCH {
            bail!("batch_size ({}) must be at most {MAX_BATCH}", c.batch_size);
        }
        if !(c.learning_rate > 0.0 && c.learning_rate.is_finite()) {
            bail!("learning_rate must be positive, got {}", c.learning_rate);
        }
        if let Some(end) = c.learning_rate_end {
            if !(end >= 0.0 && end.is_finite()) {
                bail!("learning_rate_end must be >= 0, got {end}");
            }
            let [from, to] = c.learning_rate_decay;
            if from >= to || to > MAX_STEPS_KNOB {
                bail!(
                    "learning_rate_decay must be [from, to] agent steps with from < to <= \
                     {MAX_STEPS_KNOB}, got [{from}, {to}]"
                );
            }
        } else if c.learning_rate_decay != [0, 0] {
            bail!("learning_rate_decay needs learning_rate_end, the rate it falls to");
        }
        if !(0.0..=1.0).contains(&c.gamma) {
            bail!("gamma must be in [0, 1], got {}", c.gamma);
        }
        if c.train_every == 0 || c.target_update == 0 {
            bail!("train_every and target_update must be at least 1");
        }
        for (name, e) in [
            ("epsilon_start", c.epsilon_start),
            ("epsilon_end", c.epsilon_end),
        ] {
            if !(0.0..=1.0).contains(&e) {
                bail!("{name} must be in [0, 1], got {e}");
            }
        }
        if c.quantiles > MAX_QUANTILES {
            bail!(
                "quantiles must be at most {MAX_QUANTILES}, got {}",
                c.quantiles
            );
        }
        for (name, v) in [
            ("iqn_samples", c.iqn_samples),
            ("iqn_target_samples", c.iqn_target_samples),
            ("iqn_policy_samples", c.iqn_policy_samples),
        ] {
            if v > MAX_IQN_SAMPLES || (v == 0 && name != "iqn_samples") {
                bail!("{name} must be in 1..={MAX_IQN_SAMPLES}, got {v}");
            }
        }
        if !(1..=MAX_IQN_EMBEDDING).contains(&c.iqn_embedding) {
            bail!(
                "iqn_embedding must be in 1..={MAX_IQN_EMBEDDING}, got {}",
                c.iqn_embedding
            );
        }
        if c.encoder == super::super::Encoder::Impala
            && (c.layer_norm || c.padding != Padding::Same)
        {
            bail!("encoder = \"impala\" is SAME-padded and has no layer_norm: drop padding or layer_norm");
        }
        if c.impala_channels
            .iter()
            .any(|&ch| !(1..=MAX_IMPALA_CHANNELS).contains(&ch))
        {
            bail!(
                "impala_channels must each be in 1..={MAX_IMPALA_CHANNELS}, got {:?}",
                c.impala_channels
            );
        }
        if c.impala_blocks > MAX_IMPALA_BLOCKS {
            bail!(
                "impala_blocks must be in 0..={MAX_IMPALA_BLOCKS}, got {}",
                c.impala_blocks
            );
        }
        let dopamine = (super::super::IMPALA_CHANNELS, super::super::IMPALA_BLOCKS);
        if c.encoder != super::super::Encoder::Impala
            && (c.impala_channels, c.impala_blocks) != dopamine
        {
            bail!("impala_channels and impala_blocks shape the IMPALA encoder: they need encoder = \"impala\"");
        }
        if c.iqn_samples > 0 && c.quantiles > 0 {
            bail!("iqn_samples and quantiles are two heads: ask for one of them");
        }
        if c.act_while_learning && c.act_with_target_network {
            bail!("act_while_learning acts with a copy of the online network: it cannot be combined with act_with_target_network");
        }
        if !(0.0..=1.0).contains(&c.munchausen_alpha) {
            bail!(
                "munchausen_alpha must be in [0, 1], got {}",
                c.munchausen_alpha
            );
        }
        if c.random_shift > MAX_RANDOM_SHIFT {
            bail!(
                "random_shift must be at most {MAX_RANDOM_SHIFT} pixels, got {}",
                c.random_shift
            );
        }
        if c.reset_dense_at.len() > MAX_RESETS {
            bail!(
                "reset_dense_at may list at most {MAX_RESETS} agent steps, got {}",
                c.reset_dense_at.len()
            );
        }
        let mut after = 0;
        for &t in &c.reset_dense_at {
            if t <= after || t > MAX_STEPS_KNOB {
                bail!(
                    "reset_dense_at must list increasing agent steps in 1..={MAX_STEPS_KNOB}, \
                     got {:?}",
                    c.reset_dense_at
                );
            }
            after = t;
        }
        if !(0.0..=1e6).contains(&c.life_penalty) {
            bail!("life_penalty must be in [0, 1e6], got {}", c.life_penalty);
        }
        for (name, v) in [
            ("reward_scale", c.reward_scale),
            ("reward_clip", c.reward_clip),
        ] {
            if !(v > 0.0 && v <= 1e6) {
                bail!("{name} must be in (0, 1e6], got {v}");
            }
        }
        if !(c.munchausen_tau > 0.0 && c.munchausen_tau <= 100.0) {
            bail!(
                "munchausen_tau must be in (0, 100], got {}",
                c.munchausen_tau
            );
        }
        if !(-1e6..=0.0).contains(&c.munchausen_clip) {
            bail!(
                "munchausen_clip must be in [-1e6, 0], got {}",
                c.munchausen_clip
            );
        }
        if c.munchausen_alpha > 0.0 && c.quantiles > 0 {
            bail!(
                "munchausen_alpha works with a Q-value or an implicit quantile head, not quantiles"
            );
        }
        if !(1..=MAX_HIDDEN).contains(&c.hidden) {
            bail!("hidden must be in 1..={MAX_HIDDEN}, got {}", c.hidden);
        }
        if !(1..=MAX_N_STEP).contains(&c.n_step) {
            bail!("n_step must be in 1..={MAX_N_STEP}, got {}", c.n_step);
        }
        if !(c.adam_epsilon > 0.0 && c.adam_epsilon <= 1.0) {
            bail!("adam_epsilon must be in (0, 1], got {}", c.adam_epsilon);
        }
        if !(c.clip_grad_norm >= 0.0 && c.clip_grad_norm.is_finite()) {
            bail!("clip_grad_norm must be >= 0, got {}", c.clip_grad_norm);
        }
        if let Some(p) = &c.pqn {
            c.validate_pqn(p)?;
        }
        c.validate_games()?;
        if c.checkpoint_every == 0 || c.plot_every == 0 {
            bail!("checkpoint_every and plot_every must be at least 1");
        }
        c.env.validate()?;
        Ok(())
    }

    /// The games played side by side: how many, a replay lane of enough entries for each, and the
    /// switches that assume one game.
    fn validate_games(&self) -> anyhow::Result<()> {
        let n = self.games;
        if !(1..=MAX_GAMES).contains(&n) {
            bail!("games must be in 1..={MAX_GAMES}, got {n}");
        }
        if n == 1 {
            return Ok(());
        }
        if self.pqn.is_some() {
            bail!("games is the DQN agent's: PQN plays pqn.games games (drop one of them)");
        }
        let k = self.pipeline.channels();
        if !self.replay_capacity.is_multiple_of(n) || self.replay_capacity / n <= k + 1 {
            bail!(
                "replay_capacity ({}) must be a multiple of games ({n}), with more than {} entries for each game's lane",
                self.replay_capacity,
                k + 1
            );
        }
        if self.fake_terminal_transition {
            bail!("fake_terminal_transition is the notebook's one-game loop: it cannot be combined with games > 1");
        }
        if self.act_while_learning && self.train_every < n as u64 {
            bail!(
                "act_while_learning with games side by side runs at most one update beside each pass over the games: train_every ({}) must be at least games ({n})",
                self.train_every
            );
        }
        Ok(())
    }

    /// PQN's own ranges, and the switches it has no place for (they need a replay memory, a
    /// target network or another head).
    fn validate_pqn(&self, p: &Pqn) -> anyhow::Result<()> {
        if !(1..=MAX_PQN_GAMES).contains(&p.games) {
            bail!("pqn.games must be in 1..={MAX_PQN_GAMES}, got {}", p.games);
        }
        if !(1..=MAX_STEPS_KNOB as usize).contains(&p.rollout) || p.transitions() > MAX_BATCH * 64 {
            bail!(
                "pqn.rollout must be at least 1, and pqn.games × pqn.rollout at most {}, got {} × {}",
                MAX_BATCH * 64,
                p.games,
                p.rollout
            );
        }
        if !(1..=64).contains(&p.epochs) {
            bail!("pqn.epochs must be in 1..=64, got {}", p.epochs);
        }
        if p.minibatches == 0 || !p.transitions().is_multiple_of(p.minibatches) {
            bail!(
                "pqn.minibatches must divide pqn.games × pqn.rollout ({}), got {}",
                p.transitions(),
                p.minibatches
            );
        }
        if p.minibatch() > MAX_BATCH {
            bail!(
                "a PQN minibatch (pqn.games × pqn.rollout / pqn.minibatches = {}) must be at most {MAX_BATCH}",
                p.minibatch()
            );
        }
        if !(0.0..=1.0).contains(&p.lambda) {
            bail!("pqn.lambda must be in [0, 1], got {}", p.lambda);
        }
        let unfit = [
            ("quantiles", self.quantiles > 0),
            ("iqn_samples", self.iqn_samples > 0),
            ("munchausen_alpha", self.munchausen_alpha > 0.0),
            ("prioritized", self.prioritized),
            ("random_shift", self.random_shift > 0),
            ("reset_dense_at", !self.reset_dense_at.is_empty()),
            ("act_with_target_network", self.act_with_target_network),
            ("act_while_learning", self.act_while_learning),
            ("fake_terminal_transition", self.fake_terminal_transition),
        ];
        if let Some((name, _)) = unfit.iter().find(|(_, on)| *on) {
            bail!("{name} has no place in PQN (no replay memory, no target network, a Q-value head): drop it or the [pqn] table");
        }
        Ok(())
    }
}

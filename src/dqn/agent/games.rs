//! Several games side by side ([`Config::games`]): one tick plays an agent step of every game
//! ([`Games::tick`]); the agent's loop over ticks, taking turns with the updates
//! ([`Agent::play_tick`]) or beside them ([`Agent::play_games_beside`]).

use super::*;

/// The [`Games`] of an agent's fields: a macro, so that each field is borrowed on its own and
/// the learner, the batches and the acting network stay free for the update.
macro_rules! games {
    ($agent:expr) => {
        Games {
            config: &$agent.config,
            game: &mut $agent.game,
            observer: &mut $agent.observer,
            others: &mut $agent.others,
            players: &mut $agent.players,
            finished: &mut $agent.finished,
            replay: &mut $agent.replay,
            counters: &mut $agent.counters,
            explore_rng: &mut $agent.explore_rng,
            table: &$agent.table,
            inputs: &mut $agent.inputs,
            actions: &mut $agent.actions,
            times: &mut $agent.times,
        }
    };
}

/// What a tick of the games played side by side ([`Config::games`]) touches besides the
/// networks, borrowed from an [`Agent`]: the first game and its observer, the others, every
/// game's episode in progress and the rows waiting to go out.
struct Games<'a, G> {
    config: &'a Config,
    game: &'a mut G,
    observer: &'a mut Observer,
    others: &'a mut [(G, Observer)],
    players: &'a mut [crate::dqn::Player],
    finished: &'a mut VecDeque<EpisodeRow>,
    replay: &'a mut Replay,
    counters: &'a mut Counters,
    explore_rng: &'a mut ChaCha8Rng,
    table: &'a [f32; 256],
    inputs: &'a mut Tensor<f32>,
    actions: &'a mut Vec<usize>,
    times: &'a mut LoopTimes,
}

impl<G: Game> Games<'_, G> {
    /// ALGO 2–5 for one agent step of each of the `G` games, acting with `net`: game `g` plays
    /// agent step `t₀ + g + 1`, where `t₀` is the count before; its ε is that step's, and its
    /// coin flips come after those of the games before it. A game whose episode ends queues its
    /// row (its wall time counted from `start`) and starts its next (ALGO 1).
    fn tick(&mut self, net: &mut Sequential<f32>, start: Instant) {
        let t_act = Instant::now();
        let n = self.players.len();
        let t0 = self.counters.agent_steps;
        let n_actions = self.game.n_actions();
        // ALGO 2: ε of each game's agent step. ALGO 3: a random action with probability ε, the
        // coin flips in game order; else argmax_a Q(stack, a), every game's from one pass.
        let mut random = vec![None; n];
        for (g, a) in random.iter_mut().enumerate() {
            let eps = self.config.epsilon(t0 + g as u64);
            if self.explore_rng.random::<f32>() < eps {
                *a = Some(self.explore_rng.random_range(0..n_actions));
            }
        }
        if random.iter().any(Option::is_none) {
            let per = self.inputs.len() / n;
            let observers =
                std::iter::once(&*self.observer).chain(self.others.iter().map(|o| &o.1));
            for (o, x) in observers.zip(self.inputs.data_mut().chunks_exact_mut(per)) {
                o.write_input(self.table, x);
            }
            let head = Head::of(self.config);
            crate::dqn::learner::greedy_each(&head, net, self.inputs, n_actions, self.actions);
        } else {
            self.actions.clear();
            self.actions.resize(n, 0);
        }
        for (a, r) in self.actions.iter_mut().zip(&random) {
            *a = r.unwrap_or(*a);
        }
        let t1 = Instant::now();
        // ALGO 4: play each game's action, the emulators in parallel; compose each step's frame
        // and push it on that game's stack.
        let mut lanes: Vec<(&mut G, &mut Observer)> =
            std::iter::once((&mut *self.game, &mut *self.observer))
                .chain(self.others.iter_mut().map(|(g, o)| (g, o)))
                .collect();
        let results: Vec<StepResult> = lanes
            .par_iter_mut()
            .zip(&*self.actions)
            .map(|((game, observer), &a)| {
                let r = game.step(a);
                observer.step(&**game);
                r
            })
            .collect();
        drop(lanes);
        let t2 = Instant::now();
        // ALGO 5: store each game's (a, r, done, new frame) in its lane of the replay memory, in
        // game order; a game whose episode ended starts its next (ALGO 1).
        for (g, r) in results.iter().enumerate() {
            let p = &mut self.players[g];
            let lives_lost = p.lives.map_or(0, |l| l - r.lives);
            let reward = self.config.learner_reward(r.reward, lives_lost);
            p.lives = Some(r.lives);
            p.score += r.reward as f64;
            p.length += 1;
            let done = r.terminal || (self.config.life_loss_terminal && lives_lost > 0);
            let observer = if g == 0 {
                &*self.observer
            } else {
                &self.others[g - 1].1
            };
            let frame = observer.stack().get(observer.stack().len() - 1);
            self.replay
                .push_step_in(g, self.actions[g], reward, done, frame);
            self.counters.agent_steps += 1;
            self.counters.frames += r.frames as u64;
            if r.terminal || r.truncated {
                let wall = self.counters.wall_seconds + secs(start);
                self.finish(g, wall);
                self.start(g);
            }
        }
        self.times.acting += (t1 - t_act).as_secs_f64();
        self.times.emulator += (t2 - t1).as_secs_f64();
        self.times.storing += secs(t2);
    }

    /// ALGO 1 for game `g`: reset it; compose its first frame; fill its stack with it; store it
    /// in its lane.
    fn start(&mut self, g: usize) {
        let (game, observer) = if g == 0 {
            (&mut *self.game, &mut *self.observer)
        } else {
            let (game, observer) = &mut self.others[g - 1];
            (game, observer)
        };
        game.reset();
        let first = observer.reset(game);
        self.replay.push_start_in(g, first);
        self.players[g] = crate::dqn::Player::default();
    }

    /// Queues the row of game `g`'s episode, which ended at the agent step just counted.
    fn finish(&mut self, g: usize, wall_seconds: f64) {
        let p = std::mem::take(&mut self.players[g]);
        let episode = self.counters.episodes + self.finished.len() as u64 + 1;
        let epsilon = self.config.epsilon(self.counters.agent_steps);
        let row = p.row(episode, self.counters, epsilon, wall_seconds);
        self.finished.push_back(row);
    }
}

impl<G: Game> Agent<G> {
    /// The next finished episode's row, playing every game side by side until one of them ends
    /// an episode: taking turns with the updates ([`Agent::play_tick`]), or beside them
    /// ([`Agent::play_games_beside`]).
    pub(super) fn play_games(&mut self) -> anyhow::Result<EpisodeRow> {
        while self.finished.is_empty() {
            if self.config.act_while_learning {
                self.play_games_beside()?;
            } else {
                self.play_tick()?;
            }
        }
        let row = self.finished.pop_front().expect("a finished episode");
        self.counters.episodes += 1;
        Ok(row)
    }

    /// One agent step of each of the `G` games played side by side ([`Games::tick`]), then ALGO
    /// 6 and 7 for each of those `G` agent steps in turn.
    fn play_tick(&mut self) -> anyhow::Result<()> {
        let start = Instant::now();
        let t0 = self.counters.agent_steps;
        let net = if self.config.act_with_target_network {
            self.learner.target_mut()
        } else {
            &mut self.learner.online
        };
        games!(self).tick(net, start);
        // ALGO 6 and 7 for each of the tick's agent steps in turn.
        for t in t0 + 1..=self.counters.agent_steps {
            if self.train_due(t) {
                self.sample_batch();
                let stats = self.train_step(t);
                self.landed(&stats, t, &mut EpisodeMetrics::default())?;
            }
            self.refresh_target(t..=t);
        }
        self.counters.wall_seconds += secs(start);
        Ok(())
    }

    /// The games side by side with [`Config::act_while_learning`]: ticks taking turns while no
    /// update is due; from the first tick whose agent steps hold one, each update runs on the
    /// pool while this thread plays the ticks through the one that holds the next update's step
    /// (at most one a tick: `train_every >= games`), acting with a copy of the parameters from
    /// before the update, then samples that update's batch and makes its target pass, as
    /// [`Agent::learn_while_acting`] does for one game. ALGO 7 catches up on the steps before the
    /// next update once this one has landed. The chain ends where an episode has ended (its
    /// row waits to go out): the next update, if one is due, then runs alone, so nothing is in
    /// flight when the row goes out. With every action random (ε = 1) this makes
    /// [`Agent::play_tick`]'s updates and target copies, in its order, bit for bit.
    fn play_games_beside(&mut self) -> anyhow::Result<()> {
        let start = Instant::now();
        let result = self.games_beside(start);
        self.counters.wall_seconds += secs(start);
        result
    }

    /// [`Agent::play_games_beside`], its wall time counted from `start` by the caller.
    fn games_beside(&mut self, start: Instant) -> anyhow::Result<()> {
        // Ticks taking turns until one holds an update's agent step (ALGO 2–5, then ALGO 7).
        let mut t = loop {
            let t0 = self.counters.agent_steps;
            games!(self).tick(&mut self.learner.online, start);
            let now = self.counters.agent_steps;
            match (t0 + 1..=now).find(|&t| self.train_due(t)) {
                Some(t) => {
                    self.refresh_target(t0 + 1..=t - 1);
                    self.sample_batch();
                    if self.finished.is_empty() {
                        break t;
                    }
                    // A row waits to go out: this update runs alone, as taking turns.
                    let stats = self.train_step(t);
                    self.landed(&stats, t, &mut EpisodeMetrics::default())?;
                    self.refresh_target(t..=now);
                    return Ok(());
                }
                None => {
                    self.refresh_target(t0 + 1..=now);
                    if !self.finished.is_empty() {
                        return Ok(());
                    }
                }
            }
        };
        // The copy of the target network as this chain's first update finds it.
        self.next.as_mut().expect("built").sync(&self.learner);
        loop {
            // ALGO 6 at agent step `t` on the pool, beside ALGO 2–5 of the ticks that follow.
            self.learner.adam.lr = self.config.learning_rate(t) as f32;
            let acting = self.acting.as_mut().expect("built for act_while_learning");
            acting.copy_params_from(&self.learner.online);
            let (learner, batch) = (&mut self.learner, &self.batch);
            let values = (!self.batch_values.is_empty()).then_some(&self.batch_values[..]);
            let ahead = self.ahead.as_mut().expect("built for act_while_learning");
            let next_net = self.next.as_mut().expect("built for act_while_learning");
            let ahead_values = &mut self.ahead_values;
            let sample_rng = &mut self.sample_rng;
            let mut games = games!(self);
            let (mut stats, mut update_secs, mut play_secs) = (None, 0.0, 0.0);
            let mut update = || {
                let start = Instant::now();
                stats = Some(learner.train_step_with(batch, values));
                update_secs = secs(start);
            };
            let block = Instant::now();
            let next = rayon::in_place_scope(|scope| {
                scope.spawn(move |_| update());
                let next = loop {
                    let t0 = games.counters.agent_steps;
                    games.tick(acting, start);
                    let now = games.counters.agent_steps;
                    let g = &mut games;
                    let due =
                        (t0 + 1..=now).find(|&s| train_due(g.config, g.replay, ahead.len(), s));
                    if let Some(s) = due {
                        // The next update's batch, and its target pass, off its critical path.
                        let at = Instant::now();
                        sample(g.config, g.replay, sample_rng, g.table, ahead);
                        g.times.sampling += secs(at);
                        let at = Instant::now();
                        next_net.compute(ahead, ahead_values);
                        g.times.target_pass += secs(at);
                        break Some(s);
                    }
                    if !g.finished.is_empty() {
                        break None;
                    }
                };
                play_secs = secs(block);
                next
            });
            self.times.update += update_secs;
            self.times.joining += secs(block) - play_secs;
            self.landed(
                &stats.expect("the update ran in the scope"),
                t,
                &mut EpisodeMetrics::default(),
            )?;
            let Some(next) = next else {
                // ALGO 7 for the steps played since; the row goes out.
                self.refresh_target(t..=self.counters.agent_steps);
                return Ok(());
            };
            if self.refresh_target(t..=next - 1) {
                // The pass was made with the target network before it changed: the next
                // update makes it anew, and the copy follows the target.
                self.ahead_values.clear();
                self.next.as_mut().expect("built").sync(&self.learner);
            }
            std::mem::swap(&mut self.batch, self.ahead.as_mut().expect("built"));
            std::mem::swap(&mut self.batch_values, &mut self.ahead_values);
            t = next;
            if !self.finished.is_empty() {
                // A row waits to go out: this update runs alone, with nothing left in flight.
                let stats = self.train_step(t);
                self.landed(&stats, t, &mut EpisodeMetrics::default())?;
                self.refresh_target(t..=self.counters.agent_steps);
                return Ok(());
            }
        }
    }

    /// ALGO 1 for game `g` of those played side by side ([`Games::start`]).
    pub(super) fn start(&mut self, g: usize) {
        games!(self).start(g);
    }
}

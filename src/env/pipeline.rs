//! From frames to the network's input: composing one frame per agent step, then stacking.
//!
//! A single frame cannot show which way a bullet moves, so DQN agents usually feed the last four
//! agent steps' frames together. The article compares four ways of doing this ([`Pipeline`]).
//! Each is split in two stages, so that a replay memory can store one small frame per step:
//!
//! 1. a [`Composer`] turns each agent step's last two raw frames into ONE composite 88 x 80 frame;
//! 2. a [`FrameStack`] keeps the last `k` composites (`k` = [`Pipeline::channels`]) and writes
//!    them, normalised, as the network's NHWC input: height 88, width 80, `k` channels, channel
//!    `c` being the `c`-th oldest step.
//!
//! [`Observer`] bundles both stages for an agent that is playing.

use serde::{Deserialize, Serialize};

use super::preprocess::{max_into, FRAME_HEIGHT, FRAME_LEN, FRAME_WIDTH};
use super::Game;
use crate::tensor::Border;

/// How frames become the network's input.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Pipeline {
    /// One frame per input (88 x 80 x 1): the article's baseline.
    Vanilla,
    /// The last 4 frames (88 x 80 x 4).
    Stack,
    /// The last 4 composites, each the element-wise max of the two last raw frames of its step:
    /// what the article says it does, and DeepMind's practice.
    #[default]
    StackMax,
    /// The last 4 composites, each the max of the new frame and the previous composite: what the
    /// article's code does. This is a running max since reset, so moving objects leave trails.
    StackRunningMax,
}

impl Pipeline {
    /// Frames stacked in the input: 1 for `vanilla`, 4 otherwise.
    pub fn channels(self) -> usize {
        match self {
            Pipeline::Vanilla => 1,
            _ => 4,
        }
    }
}

/// Stage 1: one composite frame per agent step. Stateful only for `stack-running-max`.
#[derive(Clone, Debug)]
pub struct Composer {
    pipeline: Pipeline,
    current: Vec<u8>,
}

impl Composer {
    /// A composer for `pipeline`; call [`reset`](Self::reset) before the first step.
    pub fn new(pipeline: Pipeline) -> Self {
        Composer {
            pipeline,
            current: vec![0; FRAME_LEN],
        }
    }

    /// The pipeline this composer implements.
    pub fn pipeline(&self) -> Pipeline {
        self.pipeline
    }

    /// Composes the first frame of an episode (forgetting any running max).
    ///
    /// `prev`, `last`: the two last raw frames; `observation`: the environment's observation
    /// (the last frame, or their max in `nature` mode). See [`step`](Self::step).
    pub fn reset(&mut self, prev: &[u8], last: &[u8], observation: &[u8]) -> &[u8] {
        match self.pipeline {
            Pipeline::StackMax => max_into(prev, last, &mut self.current),
            _ => self.current.copy_from_slice(observation),
        }
        &self.current
    }

    /// Composes the frame of one agent step:
    /// `vanilla`, `stack`: the observation; `stack-max`: `max(prev, last)`;
    /// `stack-running-max`: `max(previous composite, observation)`.
    ///
    /// # Panics
    /// If a frame is not 88 x 80.
    pub fn step(&mut self, prev: &[u8], last: &[u8], observation: &[u8]) -> &[u8] {
        match self.pipeline {
            Pipeline::Vanilla | Pipeline::Stack => self.current.copy_from_slice(observation),
            Pipeline::StackMax => max_into(prev, last, &mut self.current),
            Pipeline::StackRunningMax => {
                assert_eq!(observation.len(), FRAME_LEN, "frame has the wrong length");
                for (c, &o) in self.current.iter_mut().zip(observation) {
                    *c = (*c).max(o);
                }
            }
        }
        &self.current
    }

    /// The latest composite frame.
    pub fn frame(&self) -> &[u8] {
        &self.current
    }

    /// Sets the latest composite (to resume a running max exactly after loading a checkpoint).
    pub fn restore(&mut self, composite: &[u8]) {
        self.current.copy_from_slice(composite);
    }
}

/// Stage 2: the last `k` composite frames, oldest first.
#[derive(Clone, Debug)]
pub struct FrameStack {
    frames: Vec<Vec<u8>>,
    /// Index in `frames` of the oldest frame.
    oldest: usize,
}

impl FrameStack {
    /// An empty (all-zero) stack of `k >= 1` frames.
    pub fn new(k: usize) -> Self {
        assert!(k >= 1, "a frame stack holds at least one frame");
        FrameStack {
            frames: vec![vec![0; FRAME_LEN]; k],
            oldest: 0,
        }
    }

    /// Number of frames held.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Always false: a stack holds at least one frame.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// Fills every slot with `frame` (the start of an episode).
    pub fn reset(&mut self, frame: &[u8]) {
        for f in &mut self.frames {
            f.copy_from_slice(frame);
        }
        self.oldest = 0;
    }

    /// Drops the oldest frame and appends `frame` as the newest.
    pub fn push(&mut self, frame: &[u8]) {
        self.frames[self.oldest].copy_from_slice(frame);
        self.oldest = (self.oldest + 1) % self.frames.len();
    }

    /// The `i`-th oldest frame (0 = oldest).
    pub fn get(&self, i: usize) -> &[u8] {
        &self.frames[(self.oldest + i) % self.frames.len()]
    }

    /// Writes the stack as the network input (88 x 80 x k, NHWC, normalised with `table`).
    ///
    /// # Panics
    /// If `out.len() != 88 * 80 * k`.
    pub fn write_input(&self, table: &[f32; 256], out: &mut [f32]) {
        let k = self.frames.len();
        let mut refs: [&[u8]; 8] = [&[]; 8];
        if k <= refs.len() {
            for (i, r) in refs.iter_mut().take(k).enumerate() {
                *r = self.get(i);
            }
            write_stacked_input(&refs[..k], table, out);
        } else {
            let refs: Vec<&[u8]> = (0..k).map(|i| self.get(i)).collect();
            write_stacked_input(&refs, table, out);
        }
    }
}

/// Writes frames (oldest first) as one NHWC input of shape 88 x 80 x `frames.len()`:
/// `out[(y * 80 + x) * k + c] = table[frames[c][y * 80 + x]]`. A replay memory rebuilding a
/// stack from stored composites uses this directly.
///
/// # Panics
/// If a frame is not 88 x 80 or `out.len() != 88 * 80 * k`.
pub fn write_stacked_input(frames: &[&[u8]], table: &[f32; 256], out: &mut [f32]) {
    write_stacked_input_bordered(frames, table, Border::default(), out);
}

/// [`write_stacked_input`] into an image with a zero border around it: `out` is
/// `[top + 88 + bottom, left + 80 + right, k]`, and only the interior is written (the border
/// places keep what they hold, zeros for a fresh buffer). With the network's first padding as
/// the border ([`crate::dqn::input_border`]) the first convolution reads the input in place.
/// The values may be of any type the table holds: f32, or their bf16 roundings (a replay memory
/// writing a batch's states both ways, [`crate::tensor::Tensor::write_with_bf16`]).
///
/// # Panics
/// If a frame is not 88 x 80 or `out` has the wrong length.
pub fn write_stacked_input_bordered<V: Copy>(
    frames: &[&[u8]], table: &[V; 256], border: Border, out: &mut [V],
) {
    let k = frames.len();
    assert!(
        frames.iter().all(|f| f.len() == FRAME_LEN),
        "frame has the wrong length"
    );
    let (hb, wb) = border.around(FRAME_HEIGHT, FRAME_WIDTH);
    assert_eq!(out.len(), hb * wb * k, "input buffer has the wrong length");
    for y in 0..FRAME_HEIGHT {
        let at = ((border.top + y) * wb + border.left) * k;
        let row = &mut out[at..at + FRAME_WIDTH * k];
        let px = y * FRAME_WIDTH..(y + 1) * FRAME_WIDTH;
        match k {
            1 => {
                for (o, &p) in row.iter_mut().zip(&frames[0][px]) {
                    *o = table[p as usize];
                }
            }
            4 => {
                let (a, b, c, d) = (
                    &frames[0][px.clone()],
                    &frames[1][px.clone()],
                    &frames[2][px.clone()],
                    &frames[3][px],
                );
                for (i, o) in row.chunks_exact_mut(4).enumerate() {
                    o[0] = table[a[i] as usize];
                    o[1] = table[b[i] as usize];
                    o[2] = table[c[i] as usize];
                    o[3] = table[d[i] as usize];
                }
            }
            _ => {
                for (i, o) in row.chunks_exact_mut(k).enumerate() {
                    for (v, f) in o.iter_mut().zip(frames) {
                        *v = table[f[px.start + i] as usize];
                    }
                }
            }
        }
    }
}

/// Both stages together, fed from a [`Game`] such as [`SpaceInvaders`](super::SpaceInvaders).
#[derive(Clone, Debug)]
pub struct Observer {
    composer: Composer,
    stack: FrameStack,
}

impl Observer {
    /// An observer for `pipeline`.
    pub fn new(pipeline: Pipeline) -> Self {
        Observer {
            composer: Composer::new(pipeline),
            stack: FrameStack::new(pipeline.channels()),
        }
    }

    /// Call after `env.reset()`: composes the first frame and fills the stack with it.
    pub fn reset(&mut self, env: &impl Game) -> &[u8] {
        let (prev, last) = env.last_two_frames();
        let frame = self.composer.reset(prev, last, env.observation());
        self.stack.reset(frame);
        frame
    }

    /// Call after `env.step(..)`: composes the step's frame and pushes it; returns the composite
    /// (what a replay memory stores).
    pub fn step(&mut self, env: &impl Game) -> &[u8] {
        let (prev, last) = env.last_two_frames();
        let frame = self.composer.step(prev, last, env.observation());
        self.stack.push(frame);
        frame
    }

    /// The composer (its latest composite frame, or to restore a running max).
    pub fn composer(&mut self) -> &mut Composer {
        &mut self.composer
    }

    /// Sets the latest composite and the stack (`stack`: `k` frames, oldest first), as saved in a
    /// checkpoint, so that the next step continues exactly.
    ///
    /// # Panics
    /// If a frame is not 88 x 80 or `stack` does not hold `k` frames.
    pub fn restore(&mut self, composite: &[u8], stack: &[&[u8]]) {
        assert_eq!(stack.len(), self.stack.len(), "one frame per stack slot");
        self.composer.restore(composite);
        self.stack.reset(stack[0]);
        for f in &stack[1..] {
            self.stack.push(f);
        }
    }

    /// The latest composite frame.
    pub fn composer_frame(&self) -> &[u8] {
        self.composer.frame()
    }

    /// The stack of the last `k` composites.
    pub fn stack(&self) -> &FrameStack {
        &self.stack
    }

    /// Writes the network input (see [`FrameStack::write_input`]).
    pub fn write_input(&self, table: &[f32; 256], out: &mut [f32]) {
        self.stack.write_input(table, out)
    }

    /// Length of the network input: `88 * 80 * k`.
    pub fn input_len(&self) -> usize {
        FRAME_LEN * self.stack.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(v: u8) -> Vec<u8> {
        vec![v; FRAME_LEN]
    }

    #[test]
    fn stack_writes_nhwc_oldest_first_and_resets_to_copies() {
        let table: [f32; 256] = std::array::from_fn(|i| i as f32);
        let mut s = FrameStack::new(4);
        s.reset(&frame(1));
        s.push(&frame(2));
        s.push(&frame(3));
        let mut out = vec![0.0; FRAME_LEN * 4];
        s.write_input(&table, &mut out);
        assert_eq!(&out[..8], &[1.0, 1.0, 2.0, 3.0, 1.0, 1.0, 2.0, 3.0]);
        s.push(&frame(4));
        s.push(&frame(5));
        s.write_input(&table, &mut out);
        assert_eq!(&out[out.len() - 4..], &[2.0, 3.0, 4.0, 5.0]);
        s.reset(&frame(9));
        s.write_input(&table, &mut out);
        assert!(out.iter().all(|&v| v == 9.0));
    }

    #[test]
    fn generic_and_specialised_stacking_agree() {
        let table: [f32; 256] = std::array::from_fn(|i| i as f32 * 0.5);
        let frames: Vec<Vec<u8>> = (0..4)
            .map(|c| {
                (0..FRAME_LEN)
                    .map(|i| ((i * 7 + c * 13) % 256) as u8)
                    .collect()
            })
            .collect();
        let refs: Vec<&[u8]> = frames.iter().map(|f| f.as_slice()).collect();
        let mut fast = vec![0.0; FRAME_LEN * 4];
        write_stacked_input(&refs, &table, &mut fast);
        for y in [0, 40, 87] {
            for x in [0, 33, 79] {
                for (c, f) in frames.iter().enumerate() {
                    assert_eq!(
                        fast[(y * FRAME_WIDTH + x) * 4 + c],
                        table[f[y * FRAME_WIDTH + x] as usize]
                    );
                }
            }
        }
        let mut s = FrameStack::new(3);
        s.reset(&frames[0]);
        s.push(&frames[1]);
        s.push(&frames[2]);
        let mut three = vec![0.0; FRAME_LEN * 3];
        s.write_input(&table, &mut three);
        for i in [0, 100, FRAME_LEN - 1] {
            assert_eq!(
                three[i * 3..i * 3 + 3],
                [fast[i * 4], fast[i * 4 + 1], fast[i * 4 + 2]]
            );
        }
    }

    #[test]
    fn composers_follow_their_definitions() {
        let (a, b) = (frame(10), frame(20));
        let mut max = Composer::new(Pipeline::StackMax);
        assert!(max.step(&b, &a, &a).iter().all(|&v| v == 20));
        let mut run = Composer::new(Pipeline::StackRunningMax);
        run.reset(&a, &b, &b);
        assert!(
            run.step(&a, &a, &a).iter().all(|&v| v == 20),
            "running max remembers"
        );
        assert!(
            run.reset(&a, &a, &a).iter().all(|&v| v == 10),
            "reset forgets"
        );
        let mut plain = Composer::new(Pipeline::Stack);
        assert!(plain.step(&b, &a, &a).iter().all(|&v| v == 10));
        assert_eq!(Pipeline::Vanilla.channels(), 1);
        assert_eq!(Pipeline::StackRunningMax.channels(), 4);
    }
}

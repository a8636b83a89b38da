//! Loaders that refuse bad files: every kind of damage to a checkpoint or replay file gives an
//! error (never a panic, never a partly loaded network). Deterministic cases name each kind of
//! damage; property tests cover random truncation points, random byte flips in the header and
//! random bytes.

mod common;

use std::collections::HashMap;
use std::sync::OnceLock;

use invaders::dqn::checkpoint::{self, Checkpoint};
use invaders::dqn::{Agent, Config, Preset};
use invaders::env::SpaceInvaders;
use proptest::prelude::*;
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};

/// A real checkpoint and replay file: a short Space Invaders episode with learning.
fn files() -> &'static (Vec<u8>, Vec<u8>) {
    static FILES: OnceLock<(Vec<u8>, Vec<u8>)> = OnceLock::new();
    FILES.get_or_init(|| {
        let mut c = Config::preset(Preset::Article);
        c.learning_starts = 20;
        c.replay_capacity = 100;
        c.batch_size = 4;
        c.env.max_episode_steps = Some(40);
        c.seed = 2;
        let env = SpaceInvaders::new(&c.env, c.seed).unwrap();
        let mut agent = Agent::new(c, env);
        agent.play_episode().unwrap();
        assert!(agent.learner.adam.t > 0);
        let dir = std::env::temp_dir().join(format!("invaders-files-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        checkpoint::save_run(&dir, &agent).unwrap();
        let ckpt = std::fs::read(dir.join(checkpoint::CHECKPOINT_FILE)).unwrap();
        let replay = std::fs::read(dir.join("replay-1.safetensors")).unwrap();
        let _ = std::fs::remove_dir_all(&dir);
        (ckpt, replay)
    })
}

/// An owned copy of a safetensors file, to damage and serialise again.
struct Owned {
    tensors: Vec<(String, Dtype, Vec<usize>, Vec<u8>)>,
    meta: HashMap<String, String>,
}

impl Owned {
    fn parse(bytes: &[u8]) -> Owned {
        let (_, header) = SafeTensors::read_metadata(bytes).unwrap();
        let st = SafeTensors::deserialize(bytes).unwrap();
        Owned {
            tensors: st
                .tensors()
                .into_iter()
                .map(|(n, v)| (n, v.dtype(), v.shape().to_vec(), v.data().to_vec()))
                .collect(),
            meta: header.metadata().clone().unwrap(),
        }
    }

    /// The file, its checksum made anew for the damaged contents (so the loader's other checks
    /// are what refuse it).
    fn bytes(&self) -> Vec<u8> {
        let mut signed = Owned {
            tensors: self.tensors.clone(),
            meta: self.meta.clone(),
        };
        if signed.meta.contains_key("checksum") {
            let sum = checkpoint::tensors_checksum(
                self.tensors.iter().map(|t| (t.0.as_str(), t.3.as_slice())),
            );
            signed.meta.insert("checksum".into(), format!("{sum:08x}"));
        }
        signed.unsigned_bytes()
    }

    /// The file as it is, checksum and all.
    fn unsigned_bytes(&self) -> Vec<u8> {
        let views: Vec<_> = self
            .tensors
            .iter()
            .map(|(n, d, s, b)| (n.clone(), TensorView::new(*d, s.clone(), b).unwrap()))
            .collect();
        safetensors::serialize(views, &Some(self.meta.clone())).unwrap()
    }

    fn get(&mut self, name: &str) -> &mut (String, Dtype, Vec<usize>, Vec<u8>) {
        self.tensors.iter_mut().find(|t| t.0 == name).unwrap()
    }
}

fn ckpt_err(bytes: &[u8]) -> String {
    match checkpoint::from_bytes(bytes) {
        Ok(_) => panic!("a damaged checkpoint was accepted"),
        Err(e) => format!("{e:#}"),
    }
}

/// A snapshot of the same agent as [`files`]' checkpoint, as `train --snapshot` writes it.
fn snapshot_bytes() -> Vec<u8> {
    let c = good();
    checkpoint::snapshot_to_bytes(&c.config, &c.counters, &c.learner, &c.agent).unwrap()
}

fn good() -> Checkpoint {
    checkpoint::from_bytes(&files().0).unwrap()
}

#[test]
fn the_real_files_load() {
    let c = good();
    assert_eq!(c.config.preset, Preset::Article);
    assert!(c.agent.game.is_some());
    assert_eq!(
        c.kernels,
        Some(invaders::ops::plan::kernels(c.config.precision))
    );
    // A checkpoint written before the kernels were recorded loads, without them.
    let mut old = Owned::parse(&files().0);
    old.meta.remove("kernels");
    let old = checkpoint::from_bytes(&old.bytes()).unwrap();
    assert_eq!(old.kernels, None);
    assert_eq!(old.counters.episodes, c.counters.episodes);
    let r = checkpoint::replay_from_bytes(&files().1, &c).unwrap();
    assert_eq!(r.written(), 41);
    // Its snapshot: the online network, observer, game and counters as they were; the target
    // network a copy of the online one, Adam anew, no replay file.
    let s = checkpoint::from_bytes(&snapshot_bytes()).unwrap();
    assert!(s.snapshot && !c.snapshot);
    assert_eq!(s.counters, c.counters);
    assert_eq!((s.replay_file, s.learner.adam.t), (None, 0));
    assert_eq!(s.agent.game, c.agent.game);
    assert_eq!(s.agent.stack, c.agent.stack);
    for (a, b) in s.learner.online.params().zip(c.learner.online.params()) {
        assert_eq!(a.value.data(), b.value.data(), "{}", a.name);
    }
    for (a, b) in s.learner.target().params().zip(c.learner.online.params()) {
        assert_eq!(a.value.data(), b.value.data(), "{}", a.name);
    }
}

/// Each kind of damage, with the words its error must contain.
#[test]
fn every_kind_of_damage_is_refused_clearly() {
    let (ckpt, _) = files();
    let mut cases: Vec<(&str, Vec<u8>, &str)> = Vec::new();
    let damaged = |f: &dyn Fn(&mut Owned)| {
        let mut o = Owned::parse(ckpt);
        f(&mut o);
        o.bytes()
    };
    // A copy with metadata `key` set to `value`.
    let with_meta = |key: &str, value: &str| {
        damaged(&|o| {
            o.meta.insert(key.into(), value.into());
        })
    };
    // A copy with tensor `name`'s dtype and shape changed (where given).
    let reheaded = |name: &str, dtype: Option<Dtype>, shape: Option<Vec<usize>>| {
        damaged(&|o| {
            let t = o.get(name);
            if let Some(d) = dtype {
                t.1 = d;
            }
            if let Some(s) = &shape {
                t.2 = s.clone();
            }
        })
    };
    cases.push(("empty file", Vec::new(), "not a safetensors file"));
    cases.push((
        "random bytes",
        (0..5000u32).map(|i| (i * 7919 % 251) as u8).collect(),
        "not a safetensors file",
    ));
    cases.push((
        "truncated in the header",
        ckpt[..200].to_vec(),
        "not a safetensors file",
    ));
    cases.push((
        "truncated in the data",
        ckpt[..ckpt.len() - 1].to_vec(),
        "not a safetensors file",
    ));
    cases.push((
        "extra bytes",
        [ckpt.as_slice(), b"xx"].concat(),
        "not a safetensors file",
    ));
    cases.push((
        "renamed tensor",
        damaged(&|o| o.get("online.conv2.weight").0 = "online.conv2.kernel".into()),
        "no tensor `online.conv2.weight`",
    ));
    cases.push((
        "missing tensor",
        damaged(&|o| o.tensors.retain(|t| t.0 != "adam.v.dense1.bias")),
        "no tensor `adam.v.dense1.bias`",
    ));
    cases.push((
        "extra tensor",
        damaged(&|o| {
            o.tensors
                .push(("extra".into(), Dtype::U8, vec![1], vec![0]))
        }),
        "expected",
    ));
    cases.push((
        "wrong shape",
        reheaded("target.dense1.bias", None, Some(vec![64, 2])),
        "tensor `target.dense1.bias` has shape [64, 2], expected [128]",
    ));
    cases.push((
        "wrong dtype",
        reheaded("online.dense2.weight", Some(Dtype::I32), None),
        "tensor `online.dense2.weight` has dtype I32, expected F32",
    ));
    cases.push((
        "wrong observer dtype",
        reheaded("observer.composite", Some(Dtype::I16), Some(vec![44, 80])),
        "observer.composite",
    ));
    cases.push((
        "non-finite weight",
        damaged(&|o| o.get("online.conv1.bias").3[4..8].copy_from_slice(&f32::NAN.to_le_bytes())),
        "non-finite value at index 1",
    ));
    cases.push((
        "old format",
        damaged(&|o| {
            o.meta
                .insert("format".into(), "invaders-checkpoint-1".into());
        }),
        "unknown checkpoint format `invaders-checkpoint-1`",
    ));
    cases.push((
        "no config",
        damaged(&|o| {
            o.meta.remove("config");
        }),
        "metadata has no `config`",
    ));
    cases.push((
        "config out of range",
        damaged(&|o| {
            let c = o.meta["config"].replace("gamma = 0.97", "gamma = 7.0");
            o.meta.insert("config".into(), c);
        }),
        "gamma must be in [0, 1]",
    ));
    cases.push((
        "another preset's config (1 channel)",
        damaged(&|o| {
            let c = o.meta["config"]
                .replace("preset = \"article\"", "preset = \"article-vanilla\"")
                .replace("pipeline = \"stack-max\"", "pipeline = \"vanilla\"");
            o.meta.insert("config".into(), c);
        }),
        "tensor `online.conv1.weight` has shape [8, 8, 4, 32], expected [8, 8, 1, 32]",
    ));
    cases.push((
        "bad counters",
        damaged(&|o| {
            o.meta
                .insert("counters".into(), "{\"episodes\": -1}".into());
        }),
        "checkpoint counters",
    ));
    cases.push((
        "bad generators",
        with_meta("rngs", "{\"explore\": 3}"),
        "checkpoint random generators",
    ));
    cases.push((
        "replay file outside the run directory",
        with_meta("replay", "../../etc/passwd"),
        "bad replay file `../../etc/passwd`",
    ));
    cases.push((
        "a flipped bit in a weight",
        {
            let mut o = Owned::parse(&files().0);
            o.get("online.conv2.bias").3[1] ^= 0x40;
            o.unsigned_bytes()
        },
        "its contents are damaged",
    ));
    cases.push((
        "too many actions",
        damaged(&|o| {
            let t = o.get("online.dense2.bias");
            t.2 = vec![0];
            t.3.clear();
        }),
        "0 actions",
    ));
    cases.push((
        "unknown contents",
        with_meta("contents", "weights"),
        "unknown checkpoint contents `weights`",
    ));
    // A full checkpoint that claims to be a snapshot has tensors a snapshot lacks, and Adam's
    // steps; a snapshot with the target network or Adam's moments of a checkpoint is refused.
    cases.push((
        "a checkpoint called a snapshot",
        with_meta("contents", "snapshot"),
        "a snapshot holds no optimizer state",
    ));
    cases.push((
        "a snapshot with a target network",
        {
            let snap = Owned::parse(&snapshot_bytes());
            let full = Owned::parse(ckpt);
            let mut o = snap;
            o.tensors.extend(
                full.tensors
                    .into_iter()
                    .filter(|t| t.0.starts_with("target.")),
            );
            o.bytes()
        },
        "expected",
    ));
    for (what, bytes, needle) in &cases {
        let e = ckpt_err(bytes);
        assert!(e.contains(needle), "{what}: `{e}` lacks `{needle}`");
    }
    eprintln!("{} kinds of checkpoint damage refused", cases.len());

    // The same preset check the CLI uses.
    let c = good();
    let e = c
        .expect_preset(Preset::ArticleVanilla)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("trained with preset `article`, not `article-vanilla`"),
        "{e}"
    );
    c.expect_preset(Preset::Article).unwrap();
}

#[test]
fn damaged_replay_files_are_refused() {
    let (_, replay) = files();
    let c = good();
    let damaged = |f: &dyn Fn(&mut Owned)| {
        let mut o = Owned::parse(replay);
        f(&mut o);
        o.bytes()
    };
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        (
            "truncated",
            replay[..replay.len() / 2].to_vec(),
            "not a safetensors file",
        ),
        (
            "another checkpoint's",
            damaged(&|o| {
                o.meta.insert("episodes".into(), "7".into());
            }),
            "saved at episode 7",
        ),
        (
            "counter beyond the rows",
            damaged(&|o| {
                o.meta.insert("written".into(), "60".into());
            }),
            "tensor `replay.frames` has shape [41, 88, 80], expected [60, 88, 80]",
        ),
        (
            "action out of range",
            damaged(&|o| o.get("replay.actions").3[3] = 200),
            "replay action 200 in row 3 is out of range",
        ),
        (
            "unknown flags",
            damaged(&|o| o.get("replay.flags").3[5] = 0x80),
            "unknown flag bits 0x80 in row 5",
        ),
        (
            "non-finite reward",
            damaged(&|o| {
                o.get("replay.rewards").3[0..4].copy_from_slice(&f32::INFINITY.to_le_bytes())
            }),
            "non-finite reward in row 0",
        ),
        (
            "another capacity",
            damaged(&|o| {
                o.meta.insert("capacity".into(), "99".into());
            }),
            "capacity",
        ),
    ];
    let (_, original) = files();
    let mut flipped = original.clone();
    let n = flipped.len();
    flipped[n - 7] ^= 1;
    let e = format!(
        "{:#}",
        checkpoint::replay_from_bytes(&flipped, &c)
            .err()
            .expect("refused")
    );
    assert!(e.contains("its contents are damaged"), "{e}");
    for (what, bytes, needle) in &cases {
        // The checkpoint names the damaged file's checksum, so the other checks must refuse it.
        let mut c = good();
        if let Ok((_, h)) = SafeTensors::read_metadata(bytes) {
            if let Some(sum) = h.metadata().as_ref().and_then(|m| m.get("checksum")) {
                c.replay_checksum = u32::from_str_radix(sum, 16).ok();
            }
        }
        let e = match checkpoint::replay_from_bytes(bytes, &c) {
            Ok(_) => panic!("{what}: accepted"),
            Err(e) => format!("{e:#}"),
        };
        assert!(e.contains(needle), "{what}: `{e}` lacks `{needle}`");
    }
    eprintln!("{} kinds of replay damage refused", cases.len());
}

/// Where the tensor data starts (8-byte length + JSON header).
fn header_end(bytes: &[u8]) -> usize {
    8 + u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize
}

proptest! {
    #![proptest_config(ProptestConfig { cases: common::cases(48), ..ProptestConfig::default() })]

    /// Any truncation is an error.
    #[test]
    fn truncated_checkpoints_are_refused(frac in 0.0f64..1.0) {
        let b = &files().0;
        let cut = (frac * b.len() as f64) as usize;
        prop_assert!(checkpoint::from_bytes(&b[..cut]).is_err());
    }

    /// Flipped bytes in the header never panic; a file that still loads is a whole, valid
    /// checkpoint (a flipped digit of the seed, say, is still a valid config).
    #[test]
    fn header_byte_flips_never_panic(flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 1..4)) {
        let mut b = files().0.clone();
        let end = header_end(&b);
        for (i, x) in &flips {
            let at = i.index(end);
            b[at] ^= x;
        }
        if let Ok(c) = checkpoint::from_bytes(&b) {
            c.config.validate().unwrap();
            prop_assert!(c.learner.non_finite_param().is_none());
        }
    }

    /// Random bytes, with or without a plausible header length, are refused.
    #[test]
    fn random_bytes_are_refused(mut bytes in prop::collection::vec(any::<u8>(), 0..4096), len in 0u64..4000) {
        prop_assert!(checkpoint::from_bytes(&bytes).is_err());
        if bytes.len() >= 8 {
            bytes[..8].copy_from_slice(&len.to_le_bytes());
            prop_assert!(checkpoint::from_bytes(&bytes).is_err());
        }
        let c = good();
        prop_assert!(checkpoint::replay_from_bytes(&bytes, &c).is_err());
    }
}

/// A replay memory larger than the loader's read chunk (8 MiB of frames) comes back from its
/// file exactly, read from the file itself as `train --resume` reads it; a byte flipped in the
/// last chunk, or a file cut short, is refused.
#[test]
fn large_replay_files_stream_back_exactly() {
    use rand::{Rng, SeedableRng};
    let mut c = good();
    c.config.replay_capacity = 1500; // 1 500 frames of 7 040 bytes: two chunks
    let mut replay = c.config.new_replay();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut frame = vec![0u8; invaders::env::FRAME_LEN];
    let mut fill = |rng: &mut rand_chacha::ChaCha8Rng| {
        rng.fill(&mut frame[..]);
        frame.clone()
    };
    replay.push_start(&fill(&mut rng));
    for i in 0..1700u32 {
        let done = i % 300 == 299;
        replay.push_step(i as usize % 6, (i % 3) as f32, done, &fill(&mut rng));
        if done {
            replay.push_start(&fill(&mut rng));
        }
    }
    let dir = std::env::temp_dir().join(format!("invaders-stream-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("replay-1.safetensors");
    c.replay_checksum = Some(checkpoint::save_replay(&path, &replay, &c.counters).unwrap());
    let open = |p: &std::path::Path| {
        let f = std::fs::File::open(p).unwrap();
        let len = f.metadata().unwrap().len();
        (f, len)
    };
    let (f, len) = open(&path);
    assert!(len > 10 << 20, "{len} bytes: more than one chunk");
    let back = checkpoint::read_replay(f, len, &c).unwrap();
    assert_eq!(back.written(), replay.written());
    assert_eq!(back.parts(), replay.parts());
    let bytes = std::fs::read(&path).unwrap();
    assert_eq!(
        checkpoint::replay_from_bytes(&bytes, &c).unwrap().parts(),
        replay.parts()
    );

    // The frames' last byte lies in the second chunk.
    let frames = Owned::parse(&bytes)
        .tensors
        .iter()
        .find(|t| t.0 == "replay.frames")
        .map(|t| t.3.len())
        .unwrap();
    assert!(frames > 8 << 20);
    let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
    let end = header_end(&bytes) + header.info("replay.frames").unwrap().data_offsets.1;
    let mut flipped = bytes.clone();
    flipped[end - 1] ^= 0x10;
    std::fs::write(&path, &flipped).unwrap();
    let (f, len) = open(&path);
    let e = format!("{:#}", checkpoint::read_replay(f, len, &c).err().unwrap());
    assert!(e.contains("its contents are damaged"), "{e}");
    std::fs::write(&path, &bytes[..bytes.len() - 5000]).unwrap();
    let (f, len) = open(&path);
    let e = format!("{:#}", checkpoint::read_replay(f, len, &c).err().unwrap());
    assert!(e.contains("not a safetensors file"), "{e}");
    // A file that shrinks while it is read (its length taken before) is an error, not a panic.
    let (f, _) = open(&path);
    assert!(checkpoint::read_replay(f, bytes.len() as u64, &c).is_err());
    let _ = std::fs::remove_dir_all(&dir);
}

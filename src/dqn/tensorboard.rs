//! TensorBoard event files, so that `tensorboard --logdir runs/` shows a run's curves live.
//!
//! A run directory gets one `events.out.tfevents.T.HOST.PID.invaders` file per process that
//! trains in it: the file's version (`brain.Event:2`), a `SessionLog` START at the first agent
//! step the process will play, then one event per episode, at its last agent step, holding every
//! scalar of the episode. `metrics.csv` stays the record; these files say the same.
//!
//! **Resume.** A run resumed from a checkpoint at agent step `S` replays whatever it played after
//! `S`. TensorBoard's loaders drop those orphaned points: the Python loader purges, at a START
//! of step `S + 1` after the first, every point at step `S + 1` or later (TensorFlow's writers
//! mark a restart the same way), and the Rust data server, which ignores `SessionLog`, drops a
//! tag's points at steps not below each new point's, which the replay (exact, so at the very
//! same steps) brings for every tag. Files are named so that they sort in the order they were
//! written (`T` is at least one more than any earlier file's), as both loaders read them.
//!
//! **Format.** A file is a sequence of records: the data's length (u64, little-endian), a masked
//! CRC-32C of those 8 bytes, the data (a serialised `Event`), a masked CRC-32C of it; the mask is
//! `((c >> 15) | (c << 17)) + 0xa282ead8`. The messages below follow TensorFlow's `event.proto`
//! and `summary.proto`, field numbers included, serialised by `prost`; the checksum is `crc32c`'s.
//! (The crates written for TensorBoard fall short here: `tboard` needs `protoc` to build, and
//! `tensorboard-rs` sets the wall time itself and panics on a failed write.)
//!
//! A write that fails (a full disk) is said once and ends the file; training goes on, with
//! `metrics.csv` as it always is.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Context;
use prost::Message;

/// `tensorflow.Event`: a wall time, a step, and one of its contents.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Event {
    /// Seconds since the Unix epoch.
    #[prost(double, tag = "1")]
    pub wall_time: f64,
    /// The step (here, agent steps).
    #[prost(int64, tag = "2")]
    pub step: i64,
    /// What the event holds.
    #[prost(oneof = "What", tags = "3, 5, 7")]
    pub what: Option<What>,
}

/// The contents of an [`Event`] this program writes.
#[derive(Clone, PartialEq, prost::Oneof)]
pub enum What {
    /// The file's format version, the first event of a file: `brain.Event:2`.
    #[prost(string, tag = "3")]
    FileVersion(String),
    /// Scalars.
    #[prost(message, tag = "5")]
    Summary(Summary),
    /// A session's start (a restart, after the first).
    #[prost(message, tag = "7")]
    SessionLog(SessionLog),
}

/// `tensorflow.Summary`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Summary {
    /// The values.
    #[prost(message, repeated, tag = "1")]
    pub value: Vec<SummaryValue>,
}

/// `tensorflow.Summary.Value` with a `simple_value` (a scalar).
#[derive(Clone, PartialEq, prost::Message)]
pub struct SummaryValue {
    /// The curve's name.
    #[prost(string, tag = "1")]
    pub tag: String,
    /// The scalar (in a oneof, so that 0 is written too).
    #[prost(oneof = "Scalar", tags = "2")]
    pub value: Option<Scalar>,
}

/// The value of a [`SummaryValue`].
#[derive(Clone, PartialEq, prost::Oneof)]
pub enum Scalar {
    /// `simple_value`.
    #[prost(float, tag = "2")]
    Simple(f32),
}

/// `tensorflow.SessionLog`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct SessionLog {
    /// 1: START.
    #[prost(int32, tag = "1")]
    pub status: i32,
    /// Unused here.
    #[prost(string, tag = "2")]
    pub checkpoint_path: String,
    /// A note.
    #[prost(string, tag = "3")]
    pub msg: String,
}

/// `SessionLog.START`.
pub const SESSION_START: i32 = 1;

/// The file names' prefix.
pub const PREFIX: &str = "events.out.tfevents.";

fn masked_crc(bytes: &[u8]) -> u32 {
    let c = crc32c::crc32c(bytes);
    c.rotate_right(15).wrapping_add(0xa282_ead8)
}

/// One record: length, its checksum, the data, its checksum.
pub fn record(data: &[u8]) -> Vec<u8> {
    let len = (data.len() as u64).to_le_bytes();
    let mut out = Vec::with_capacity(data.len() + 16);
    out.extend_from_slice(&len);
    out.extend_from_slice(&masked_crc(&len).to_le_bytes());
    out.extend_from_slice(data);
    out.extend_from_slice(&masked_crc(data).to_le_bytes());
    out
}

/// Reads the events of one file, checking every record's checksums.
pub fn read_events(path: &Path) -> anyhow::Result<Vec<Event>> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mut events = Vec::new();
    let mut rest = &bytes[..];
    while !rest.is_empty() {
        let bad = || anyhow::anyhow!("{}: a damaged record", path.display());
        if rest.len() < 12 {
            return Err(bad());
        }
        let len = u64::from_le_bytes(rest[..8].try_into().expect("8 bytes")) as usize;
        if u32::from_le_bytes(rest[8..12].try_into().expect("4 bytes")) != masked_crc(&rest[..8])
            || rest.len() < 16 + len
        {
            return Err(bad());
        }
        let data = &rest[12..12 + len];
        let crc = u32::from_le_bytes(rest[12 + len..16 + len].try_into().expect("4 bytes"));
        if crc != masked_crc(data) {
            return Err(bad());
        }
        events.push(Event::decode(data).map_err(|_| bad())?);
        rest = &rest[16 + len..];
    }
    Ok(events)
}

/// The event files of a directory, in the order they were written (their names' order).
pub fn event_files(dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("cannot read {}", dir.display()))?
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with(PREFIX))
        .map(|e| e.path())
        .collect();
    files.sort();
    Ok(files)
}

/// Each tag's points `(step, wall time, value)`, in the order written.
pub type Scalars = std::collections::BTreeMap<String, Vec<(i64, f64, f32)>>;

/// What TensorBoard shows of a directory's scalars, as its Python loader reads it: every file in
/// name order, a START after the first purging each point at its step or later.
pub fn read_scalars(dir: &Path) -> anyhow::Result<Scalars> {
    let mut tags = Scalars::new();
    let mut started = false;
    for file in event_files(dir)? {
        for e in read_events(&file)? {
            match e.what {
                Some(What::SessionLog(s)) if s.status == SESSION_START => {
                    if started {
                        for points in tags.values_mut() {
                            points.retain(|p| p.0 < e.step);
                        }
                    }
                    started = true;
                }
                Some(What::Summary(s)) => {
                    for v in s.value {
                        if let Some(Scalar::Simple(x)) = v.value {
                            tags.entry(v.tag)
                                .or_default()
                                .push((e.step, e.wall_time, x));
                        }
                    }
                }
                _ => {}
            }
        }
    }
    Ok(tags)
}

/// Seconds since the Unix epoch, now.
pub fn now() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// An event file being written (see the module).
pub struct EventWriter {
    file: Option<File>,
    path: PathBuf,
}

impl EventWriter {
    /// A new event file in `dir` whose first step will be `first_step`: its version, then a
    /// START at that step (a restart's mark, for TensorBoard, after a directory's first).
    pub fn create(dir: &Path, first_step: i64) -> anyhow::Result<EventWriter> {
        let mut w = EventWriter::open(dir)?;
        w.write(&Event {
            wall_time: now(),
            step: first_step,
            what: Some(What::SessionLog(SessionLog {
                status: SESSION_START,
                checkpoint_path: String::new(),
                msg: String::new(),
            })),
        })?;
        Ok(w)
    }

    /// A new event file in `dir` with its version only, for points added to a finished run (an
    /// experiment's evaluations): no START, which would mark a restart.
    pub fn append_only(dir: &Path) -> anyhow::Result<EventWriter> {
        EventWriter::open(dir)
    }

    fn open(dir: &Path) -> anyhow::Result<EventWriter> {
        let secs = now() as u64;
        // After every earlier file, so that the loaders read them in the order written.
        let last = event_files(dir)?
            .iter()
            .filter_map(|p| {
                p.file_name()?
                    .to_string_lossy()
                    .strip_prefix(PREFIX)?
                    .split('.')
                    .next()?
                    .parse::<u64>()
                    .ok()
            })
            .max();
        let t = last.map_or(secs, |l| secs.max(l + 1));
        let host = hostname();
        let path = dir.join(format!(
            "{PREFIX}{t:010}.{host}.{}.invaders",
            std::process::id()
        ));
        let file = std::fs::OpenOptions::new()
            .create_new(true)
            .write(true)
            .open(&path)
            .with_context(|| format!("cannot create {}", path.display()))?;
        let mut w = EventWriter {
            file: Some(file),
            path,
        };
        w.write(&Event {
            wall_time: now(),
            step: 0,
            what: Some(What::FileVersion("brain.Event:2".into())),
        })?;
        Ok(w)
    }

    /// The file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// One event holding the scalars `values` at `step`, written through to the file.
    pub fn scalars(
        &mut self, step: i64, wall_time: f64, values: &[(&str, f64)],
    ) -> anyhow::Result<()> {
        self.write(&Event {
            wall_time,
            step,
            what: Some(What::Summary(Summary {
                value: values
                    .iter()
                    .map(|(tag, v)| SummaryValue {
                        tag: tag.to_string(),
                        value: Some(Scalar::Simple(*v as f32)),
                    })
                    .collect(),
            })),
        })
    }

    fn write(&mut self, e: &Event) -> anyhow::Result<()> {
        let Some(file) = &mut self.file else {
            return Ok(());
        };
        let bytes = record(&e.encode_to_vec());
        let written = file.write_all(&bytes).and_then(|()| file.flush());
        if let Err(err) = written {
            self.file = None;
            return Err(err).with_context(|| format!("cannot write {}", self.path.display()));
        }
        Ok(())
    }
}

/// This machine's name (TensorFlow puts it in the file name), or `localhost`.
fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty() && h.chars().all(|c| c.is_ascii_alphanumeric() || c == '-'))
        .unwrap_or_else(|| "localhost".into())
}

//! A small safe wrapper over the Arcade Learning Environment (ALE 0.6, through `ale-sys`).
//!
//! The ALE emulates an Atari 2600 (with the Stella emulator) and knows, for each supported game,
//! where the score and the lives live in the console's RAM, so it can report rewards and the end
//! of a game. This wrapper owns one emulator instance and exposes only what the environment needs.
//!
//! Three ALE quirks shape it:
//!
//! * Settings (seed, frame skip, sticky actions, ...) only take effect when a ROM is loaded, so
//!   they are all passed to [`Ale::new`], which applies them and then loads the ROM.
//! * ALE picks the game's reward and game-over logic by the ROM's *file name*. The ROM is therefore
//!   always copied to a private temporary directory as `space_invaders.bin` before loading.
//! * Loading a missing file makes the C++ side throw, which aborts the process; every check that
//!   can fail is done in Rust first.
//!
//! An emulator may move to another thread (`Send`, so that several games step in parallel), but
//! it is used by one thread at a time (not `Sync`): each `ALEInterface` owns all of its state,
//! and the ALE keeps none per thread (`vendor/ale-sys/ale` holds no `thread_local`); the little
//! global state it has is written while a ROM loads, which is serialised (`LOAD_LOCK`).

use std::ffi::CString;
use std::fs;
use std::os::raw::c_int;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use super::EnvError;

/// Height of the Atari screen in pixels.
pub const SCREEN_HEIGHT: usize = 210;
/// Width of the Atari screen in pixels.
pub const SCREEN_WIDTH: usize = 160;
/// Bytes of one RGB screen (`210 * 160 * 3`, row-major, interleaved R, G, B).
pub const SCREEN_RGB_LEN: usize = SCREEN_HEIGHT * SCREEN_WIDTH * 3;

/// The file name ALE 0.6 recognises as Space Invaders.
pub const ROM_FILE_NAME: &str = "space_invaders.bin";

/// Stella keeps a little global state (for example the last cartridge's description string) that
/// is written while a ROM loads; loading is serialised process-wide so parallel threads are safe.
static LOAD_LOCK: Mutex<()> = Mutex::new(());

/// Settings applied to the emulator before the ROM loads.
#[derive(Clone, Debug)]
pub struct AleSettings {
    /// ALE's own random seed (only used by ALE's internal sticky actions, which we keep off).
    pub random_seed: i32,
    /// ALE's `repeat_action_probability`. The environment implements sticky actions itself and
    /// passes 0 here (see `space_invaders.rs` for why).
    pub repeat_action_probability: f32,
    /// Print ALE's informational console output (off: only errors are printed).
    pub verbose: bool,
}

/// One emulator with Space Invaders loaded. Frame skip is always 1 inside the emulator and colour
/// averaging is off, so every [`act`](Ale::act) is exactly one raw frame.
///
/// Invariant, which every `unsafe` call below relies on: `ptr` is the non-null `ALEInterface` that
/// `ALE_new` returned, owned by this value alone (`Ale` is neither `Clone` nor `Sync`, and the
/// pointer never leaves it), with the ROM loaded once [`Ale::new`] has returned; it is deleted
/// only in `Drop`. ALE's C functions are then sound to call with it from whichever one thread
/// holds the value.
pub struct Ale {
    ptr: *mut ale_sys::ALEInterface,
    minimal_actions: Vec<i32>,
    legal_actions: Vec<i32>,
}

impl Ale {
    /// Creates an emulator, applies `settings` and loads the ROM: the bundled Space Invaders ROM
    /// when `rom` is `None`, otherwise the file at `rom` (checked to exist and be non-empty).
    pub fn new(settings: &AleSettings, rom: Option<&Path>) -> Result<Self, EnvError> {
        let rom_bytes = match rom {
            None => ale::BundledRom::SpaceInvaders.data().to_vec(),
            Some(path) => read_rom(path)?,
        };
        let temp_rom = |source| EnvError::TempRom {
            dir: std::env::temp_dir(),
            source,
        };
        let dir = PrivateDir::new().map_err(temp_rom)?;
        let rom_path = dir.0.join(ROM_FILE_NAME);
        fs::write(&rom_path, &rom_bytes).map_err(temp_rom)?;
        let c_path = CString::new(rom_path.to_string_lossy().into_owned())
            .map_err(|_| temp_rom(std::io::Error::other("NUL byte in the path")))?;

        let _guard = LOAD_LOCK.lock().unwrap_or_else(|e| e.into_inner());
        // The logger level is global to the process; set it before the constructor, which
        // already prints a banner at the info level.
        // SAFETY: `setLoggerMode` takes a plain integer and sets a process-wide level; the load
        // lock held here keeps it from racing another thread's emulator construction.
        unsafe { ale_sys::setLoggerMode(if settings.verbose { 0 } else { 2 }) };
        // SAFETY: `ALE_new` takes no arguments; its result is checked for null before any use,
        // and under the load lock Stella's global state is written by one thread at a time.
        let ptr = unsafe { ale_sys::ALE_new() };
        if ptr.is_null() {
            return Err(EnvError::Ale("ALE_new returned null".into()));
        }
        let mut ale = Ale {
            ptr,
            minimal_actions: Vec::new(),
            legal_actions: Vec::new(),
        };
        ale.set_int("random_seed", settings.random_seed);
        ale.set_float(
            "repeat_action_probability",
            settings.repeat_action_probability,
        );
        ale.set_int("frame_skip", 1);
        ale.set_bool("color_averaging", false);
        // SAFETY: `ale.ptr` is the live emulator just created; `c_path` is a NUL-terminated
        // string that outlives the call, naming a file written above (so the C++ side does not
        // throw on a missing file); the load lock serialises Stella's global state.
        unsafe { ale_sys::loadROM(ale.ptr, c_path.as_ptr()) };
        drop(dir); // the emulator has read the ROM into memory

        ale.minimal_actions =
            ale.action_set(ale_sys::getMinimalActionSize, ale_sys::getMinimalActionSet);
        ale.legal_actions = ale.action_set(ale_sys::getLegalActionSize, ale_sys::getLegalActionSet);
        if ale.minimal_actions.is_empty() || ale.legal_actions.len() != 18 {
            return Err(EnvError::Ale(format!(
                "unexpected action sets after loading the ROM: minimal {:?}, legal {} actions",
                ale.minimal_actions,
                ale.legal_actions.len()
            )));
        }
        Ok(ale)
    }

    fn set_int(&mut self, key: &str, value: i32) {
        let key = CString::new(key).expect("static key");
        // SAFETY: `self.ptr` is the live emulator this `Ale` owns (see the type's invariant);
        // `key` is a NUL-terminated string that lives until the call returns.
        unsafe { ale_sys::setInt(self.ptr, key.as_ptr(), value as c_int) };
    }

    fn set_float(&mut self, key: &str, value: f32) {
        let key = CString::new(key).expect("static key");
        // SAFETY: `self.ptr` is the live emulator this `Ale` owns (see the type's invariant);
        // `key` is a NUL-terminated string that lives until the call returns.
        unsafe { ale_sys::setFloat(self.ptr, key.as_ptr(), value) };
    }

    fn set_bool(&mut self, key: &str, value: bool) {
        let key = CString::new(key).expect("static key");
        // SAFETY: `self.ptr` is the live emulator this `Ale` owns (see the type's invariant);
        // `key` is a NUL-terminated string that lives until the call returns.
        unsafe { ale_sys::setBool(self.ptr, key.as_ptr(), value) };
    }

    fn action_set(
        &mut self, size: unsafe extern "C" fn(*mut ale_sys::ALEInterface) -> c_int,
        fill: unsafe extern "C" fn(*mut ale_sys::ALEInterface, *mut c_int),
    ) -> Vec<i32> {
        // SAFETY: `self.ptr` is the live emulator this `Ale` owns (see the type's invariant), and
        // `size` is one of ALE's action-set size functions, which only read it.
        let n = unsafe { size(self.ptr) }.max(0) as usize;
        let mut v = vec![0 as c_int; n];
        // SAFETY: `fill` is the fill function paired with `size`, which writes exactly `n`
        // values (the size it just reported, the ROM unchanged in between) into `v`'s `n`.
        unsafe { fill(self.ptr, v.as_mut_ptr()) };
        v
    }

    /// The game's minimal action set as ALE action ids (Space Invaders: NOOP, FIRE, RIGHT, LEFT,
    /// RIGHTFIRE, LEFTFIRE = 0, 1, 3, 4, 11, 12).
    pub fn minimal_action_set(&self) -> &[i32] {
        &self.minimal_actions
    }

    /// All 18 joystick actions as ALE action ids (0..18).
    pub fn legal_action_set(&self) -> &[i32] {
        &self.legal_actions
    }

    /// Emulates one frame with the given ALE action id and returns the reward it earned.
    ///
    /// # Panics
    /// If `action` is not one of the 18 legal ids.
    pub fn act(&mut self, action: i32) -> i32 {
        assert!((0..18).contains(&action), "illegal ALE action id {action}");
        // SAFETY: `self.ptr` is the live emulator this `Ale` owns (see the type's invariant); `action` was checked
        // to be a legal id, so the emulator does not index out of its action table.
        unsafe { ale_sys::act(self.ptr, action as c_int) }
    }

    /// True once the game is over (all lives lost).
    pub fn game_over(&self) -> bool {
        // SAFETY: `self.ptr` is the live emulator this `Ale` owns (see the type's invariant).
        unsafe { ale_sys::game_over(self.ptr) }
    }

    /// Starts a new game (ALE runs a fixed, deterministic sequence of frames to do so).
    pub fn reset_game(&mut self) {
        // SAFETY: `self.ptr` is the live emulator this `Ale` owns (see the type's invariant).
        unsafe { ale_sys::reset_game(self.ptr) }
    }

    /// Lives left, as read from the console's RAM (Space Invaders starts with 3).
    pub fn lives(&self) -> i32 {
        // SAFETY: `self.ptr` is the live emulator this `Ale` owns (see the type's invariant).
        unsafe { ale_sys::lives(self.ptr) }
    }

    /// Frames emulated since the emulator was created.
    pub fn frame_number(&self) -> i32 {
        // SAFETY: `self.ptr` is the live emulator this `Ale` owns (see the type's invariant).
        unsafe { ale_sys::getFrameNumber(self.ptr) }
    }

    /// Frames emulated since the last reset (ALE's own count, which includes its reset frames).
    pub fn episode_frame_number(&self) -> i32 {
        // SAFETY: `self.ptr` is the live emulator this `Ale` owns (see the type's invariant).
        unsafe { ale_sys::getEpisodeFrameNumber(self.ptr) }
    }

    /// Copies the current screen as RGB (`210 * 160 * 3` bytes) into `out`.
    ///
    /// # Panics
    /// If `out.len() != SCREEN_RGB_LEN`.
    pub fn screen_rgb(&self, out: &mut [u8]) {
        assert_eq!(
            out.len(),
            SCREEN_RGB_LEN,
            "RGB screen buffer has the wrong length"
        );
        // SAFETY: `self.ptr` is the live emulator this `Ale` owns (see the type's invariant); ALE writes
        // 210·160·3 bytes, and `out` was checked to hold exactly that many.
        unsafe { ale_sys::getScreenRGB(self.ptr, out.as_mut_ptr()) };
    }

    /// Serialises the whole emulator state, including ALE's random generator (about 7.7 KB).
    pub fn save_state(&self) -> Vec<u8> {
        // SAFETY: `self.ptr` is the live emulator this `Ale` owns (see the type's invariant);
        // `state` is a fresh state object owned here, encoded into a buffer of exactly the
        // length `encodeStateLen` reported for it, and deleted once, after its last use.
        unsafe {
            let state = ale_sys::cloneSystemState(self.ptr);
            let len = ale_sys::encodeStateLen(state).max(0) as usize;
            let mut buf = vec![0u8; len];
            ale_sys::encodeState(state, buf.as_mut_ptr().cast(), len as c_int);
            ale_sys::deleteState(state);
            buf
        }
    }

    /// Restores a state made by [`save_state`](Ale::save_state) (of this or another emulator with
    /// the same ROM).
    pub fn restore_state(&mut self, bytes: &[u8]) -> Result<(), EnvError> {
        if bytes.is_empty() || bytes.len() > c_int::MAX as usize {
            return Err(EnvError::BadState(
                "empty or oversized emulator state".into(),
            ));
        }
        // SAFETY: `bytes` is readable for the `len` passed (checked to fit a `c_int`);
        // `decodeState` returns a fresh state object or null (checked before use); `self.ptr`
        // is the live emulator this `Ale` owns; the state is deleted once, after its last use.
        unsafe {
            let state = ale_sys::decodeState(bytes.as_ptr().cast(), bytes.len() as c_int);
            if state.is_null() {
                return Err(EnvError::BadState(
                    "ALE could not decode the emulator state".into(),
                ));
            }
            ale_sys::restoreSystemState(self.ptr, state);
            ale_sys::deleteState(state);
        }
        Ok(())
    }
}

// SAFETY: the interface behind `ptr` is owned by this value alone and holds all of its own
// state; the ALE and Stella keep no thread-local state (no `thread_local`, `__thread` or
// `pthread_getspecific` in `vendor/ale-sys/ale`), and their few globals (the cartridge
// description, the TIA's playfield table) are written only while a ROM loads, under `LOAD_LOCK`,
// with the same values each time. Moving the value to another thread and calling the ALE there
// is therefore sound; `&Ale` is not shared between threads (`Ale` is not `Sync`).
unsafe impl Send for Ale {}

impl Drop for Ale {
    fn drop(&mut self) {
        // SAFETY: `self.ptr` came from `ALE_new`, is owned by this value alone and is deleted
        // here exactly once; nothing uses it afterwards.
        unsafe { ale_sys::ALE_del(self.ptr) }
    }
}

/// The Space Invaders ROMs this program knows: `(size, CRC-32)`. The bundled one is the only dump
/// here; another file would make ALE emulate whatever it holds (random bytes spin forever on an
/// illegal instruction, a 1-byte file overflows the stack), so anything else is refused.
const KNOWN_ROMS: [(usize, u32); 1] = [(4096, 0xd1ef_5725)];

/// Reads a user-supplied ROM, turning every failure into a clear error before ALE sees it:
/// missing, unreadable, empty, or not a Space Invaders ROM ([`KNOWN_ROMS`]).
fn read_rom(path: &Path) -> Result<Vec<u8>, EnvError> {
    let bytes = read_rom_file(path)?;
    let crc = crc32fast::hash(&bytes);
    if !KNOWN_ROMS.contains(&(bytes.len(), crc)) {
        return Err(EnvError::RomUnknown {
            path: path.to_path_buf(),
            size: bytes.len(),
            crc,
        });
    }
    Ok(bytes)
}

fn read_rom_file(path: &Path) -> Result<Vec<u8>, EnvError> {
    let meta = match fs::metadata(path) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(EnvError::RomNotFound(path.to_path_buf()))
        }
        Err(source) => {
            return Err(EnvError::RomUnreadable {
                path: path.to_path_buf(),
                source,
            })
        }
    };
    if !meta.is_file() || meta.len() == 0 {
        return Err(EnvError::RomEmpty(path.to_path_buf()));
    }
    fs::read(path).map_err(|source| EnvError::RomUnreadable {
        path: path.to_path_buf(),
        source,
    })
}

/// A freshly created directory under the system temp dir, removed (with its contents) on drop.
struct PrivateDir(PathBuf);

impl PrivateDir {
    fn new() -> std::io::Result<Self> {
        static COUNTER: AtomicU64 = AtomicU64::new(0);
        let base = std::env::temp_dir();
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0);
        for _ in 0..100 {
            let n = COUNTER.fetch_add(1, Ordering::Relaxed);
            let dir = base.join(format!("invaders-rom-{}-{nanos}-{n}", std::process::id()));
            match fs::create_dir(&dir) {
                Ok(()) => return Ok(PrivateDir(dir)),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                Err(e) => return Err(e),
            }
        }
        Err(std::io::Error::other(
            "could not create a private temporary directory",
        ))
    }
}

impl Drop for PrivateDir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
    }
}

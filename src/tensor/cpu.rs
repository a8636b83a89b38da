//! What this CPU runs, checked once: the one feature test every kernel family honours, and the
//! one wrapper that compiles a loop for AVX-512.
//!
//! The hand-written kernels (the gather and scatter GEMMs, the Winograd transforms, the sparse
//! and background products, the transposes) have AVX-512F and FMA loops; [`avx512`] says
//! whether those run: this CPU has both, and neither `INVADERS_NO_SIMD` nor
//! `INVADERS_NO_AVX512` is set. Where they do not, [`avx2`] says whether the AVX2 and FMA family
//! runs (the gather and scatter GEMMs, Winograd's transforms and, where their shapes allow,
//! acting's sparse and background products; `INVADERS_NO_AVX512` makes an AVX-512 host run it),
//! and everything else takes its portable loop. faer's GEMM checks the CPU itself
//! ([`faer_path`]). `INVADERS_NO_SIMD` is the switch back to the portable code on any host
//! (im2col + faer in the layers, the portable loops in the kernels), for A/B timing in one
//! session and for testing the portable path there.
//! `INVADERS_NO_BF16` is the narrower switch: the AVX-512 kernels stay, AVX512-BF16 goes, as on
//! an AVX-512 CPU without it (Intel Skylake-SP to Ice Lake), so bf16 asked for runs in f32.
//! Where AVX512-BF16 runs and the CPU has AMX tiles as well (Intel Sapphire Rapids and later),
//! the bf16 gather GEMM runs on the tiles ([`amx`]); `INVADERS_NO_AMX` keeps it on
//! `vdpbf16ps`, as on a CPU without them. The four are read once, at the first call, so a
//! process runs one way throughout.
//!
//! The choice of a kernel has two tiers, and this module is the second. [`crate::ops::plan`]
//! chooses the algorithm of each product (the gather GEMM, Winograd, the sparse or background
//! product, im2col + faer; f32 or bf16), and reads this module only for that. The family it
//! chose then picks its instruction set on every call, here and nowhere else: the f32 families
//! (gather and scatter GEMMs, Winograd's transforms, the sparse and background products, the
//! transposes) by [`path`] (or [`avx512`] where they have no AVX2 loop), the bf16 gather GEMM
//! by [`bf16_gather_path`] and the other bf16 products by [`avx512_bf16`].
//! The plan only names what these say, for the record ([`crate::ops::plan::kernels`]).
//!
//! Each hand-written kernel family records which of its loops ran ([`took`], read back by
//! [`paths`]), per thread, on the thread that called it: a test can then prove that the
//! AVX-512 kernel it meant to check is the one that ran, and not the portable twin (or the
//! reverse with `INVADERS_NO_SIMD=1`). The record is one thread-local increment per call.

use std::cell::Cell;
use std::sync::OnceLock;

/// The CPU features the kernels use, as detected once per process.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Features {
    /// AVX-512F and FMA, and neither `INVADERS_NO_SIMD` nor `INVADERS_NO_AVX512` set: the
    /// AVX-512 kernels run.
    pub avx512: bool,
    /// AVX2 and FMA where the AVX-512 kernels do not run, and `INVADERS_NO_SIMD` unset: the AVX2
    /// family runs (the gather and scatter GEMMs and Winograd for a convolution's training
    /// products, the sparse and background products for acting where their shapes allow; see
    /// [`crate::ops::plan`]). `INVADERS_NO_AVX512` makes an AVX-512 host run this family (faer's
    /// GEMM keeps its AVX-512 kernels there, [`faer_path`]).
    pub avx2: bool,
    /// That, AVX512-BF16 (`vdpbf16ps`: AMD Zen 4 and 5, Intel Cooper Lake and later), and
    /// `INVADERS_NO_BF16` unset.
    pub avx512_bf16: bool,
    /// Whether `INVADERS_NO_BF16` turned AVX512-BF16 off on a CPU that runs it.
    pub bf16_switched_off: bool,
    /// That AVX512-BF16 runs, the CPU has AMX's tiles and their bf16 product (AMX-TILE,
    /// AMX-BF16), the operating system saves them with a thread's state and let this process
    /// use them, and `INVADERS_NO_AMX` is unset: the bf16 gather GEMM runs on the tiles.
    pub amx: bool,
}

/// What this CPU has, whatever the environment says: AVX-512F and FMA, AVX2 and FMA,
/// AVX512-BF16, AMX's tiles turned on by the operating system (nothing off x86-64).
fn detect() -> Features {
    #[cfg(target_arch = "x86_64")]
    let (avx512, avx2, avx512_bf16) = {
        let fma = is_x86_feature_detected!("fma");
        (
            is_x86_feature_detected!("avx512f") && fma,
            is_x86_feature_detected!("avx2") && fma,
            is_x86_feature_detected!("avx512bf16"),
        )
    };
    #[cfg(not(target_arch = "x86_64"))]
    let (avx512, avx2, avx512_bf16) = (false, false, false);
    Features {
        avx512,
        avx2,
        avx512_bf16,
        bf16_switched_off: false,
        amx: amx_on_cpu(),
    }
}

/// Whether this CPU has AMX-TILE and AMX-BF16 (CPUID leaf 7: EDX bits 24 and 22) and the
/// operating system has turned the tile state on (XCR0 bits 17 and 18). Not whether this
/// process may use it: [`amx_permitted`].
fn amx_on_cpu() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{__cpuid, __cpuid_count};
        let (max, osxsave) = (__cpuid(0).eax, __cpuid(1).ecx & (1 << 27) != 0);
        if max < 7 || !osxsave {
            return false;
        }
        // Leaf 7 exists where leaf 0 says so.
        let edx = __cpuid_count(7, 0).edx;
        if edx & (1 << 24) == 0 || edx & (1 << 22) == 0 {
            return false;
        }
        let (lo, _hi): (u32, u32);
        // SAFETY: XGETBV with ECX = 0 runs where CPUID says the OS has XSAVE on (OSXSAVE).
        unsafe {
            std::arch::asm!("xgetbv", in("ecx") 0, out("eax") lo, out("edx") _hi,
                options(nomem, nostack, preserves_flags));
        }
        lo & (0b11 << 17) == 0b11 << 17
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Asks Linux to let this process use AMX's tile data (`arch_prctl(ARCH_REQ_XCOMP_PERM,
/// XFEATURE_XTILEDATA)`, since Linux 5.16): without it the first tile instruction kills the
/// process. Granted once for the whole process; `false` where refused or not Linux.
fn amx_permitted() -> bool {
    #[cfg(all(target_arch = "x86_64", target_os = "linux"))]
    {
        const SYS_ARCH_PRCTL: i64 = 158;
        const ARCH_REQ_XCOMP_PERM: i64 = 0x1023;
        const XFEATURE_XTILEDATA: i64 = 18;
        let ret: i64;
        // SAFETY: the arch_prctl system call with these arguments only changes which state
        // the kernel saves for this process; it reads and writes no memory of ours.
        unsafe {
            std::arch::asm!("syscall",
                inlateout("rax") SYS_ARCH_PRCTL => ret,
                in("rdi") ARCH_REQ_XCOMP_PERM, in("rsi") XFEATURE_XTILEDATA,
                out("rcx") _, out("r11") _, options(nostack));
        }
        ret == 0
    }
    #[cfg(not(all(target_arch = "x86_64", target_os = "linux")))]
    false
}

/// The features of this CPU (detected on the first call, then cached).
pub fn features() -> Features {
    static FEATURES: OnceLock<Features> = OnceLock::new();
    *FEATURES.get_or_init(|| {
        let simd = std::env::var_os("INVADERS_NO_SIMD").is_none();
        let no_avx512 = std::env::var_os("INVADERS_NO_AVX512").is_some();
        let has = detect();
        let avx512 = has.avx512 && simd && !no_avx512;
        let avx2 = !avx512 && has.avx2 && simd;
        let bf16 = avx512 && has.avx512_bf16;
        let off = std::env::var_os("INVADERS_NO_BF16").is_some();
        let no_amx = std::env::var_os("INVADERS_NO_AMX").is_some();
        let amx = bf16 && !off && has.amx && !no_amx && amx_permitted();
        Features {
            avx512,
            avx2,
            avx512_bf16: bf16 && !off,
            bf16_switched_off: bf16 && off,
            amx,
        }
    })
}

/// The instruction set faer's GEMM takes on this CPU (im2col's products, the dense layers off
/// AVX-512, the quantile embedding): faer checks the CPU itself (AVX-512F, else AVX2 and FMA,
/// else neither; here by the crate's own feature test, whose FMA every AVX-512F CPU has), so
/// `INVADERS_NO_SIMD` and `INVADERS_NO_AVX512` do not reach it. That is the kernel of its
/// products above 16³ multiply-adds (the `private-gemm-x86` crate); smaller ones take the
/// `nano-gemm` and `gemm` crates, which stop at AVX2 without their `nightly` feature.
pub fn faer_path() -> Path {
    match detect() {
        Features { avx512: true, .. } => Path::Avx512,
        Features { avx2: true, .. } => Path::Avx2,
        _ => Path::Portable,
    }
}

/// Whether the AVX2 family runs (see [`Features::avx2`]).
#[inline]
pub fn avx2() -> bool {
    features().avx2
}

/// Whether the AVX512-BF16 kernels may run (AVX-512 as [`avx512`], AVX512-BF16, and
/// `INVADERS_NO_BF16` unset).
#[inline]
pub fn avx512_bf16() -> bool {
    features().avx512_bf16
}

/// Whether the bf16 gather GEMM runs on AMX tiles (see [`Features::amx`]).
#[inline]
pub fn amx() -> bool {
    features().amx
}

/// Whether the AVX-512 kernels run (see the module documentation).
#[inline]
pub fn avx512() -> bool {
    features().avx512
}

/// Why the AVX-512 kernels do not run on this host, or `None` if they do: the missing CPU
/// feature (`avx512f`, `fma`), another architecture, `INVADERS_NO_SIMD` or `INVADERS_NO_AVX512`.
pub fn why_portable() -> Option<String> {
    if avx512() {
        return None;
    }
    if std::env::var_os("INVADERS_NO_SIMD").is_some() {
        return Some("INVADERS_NO_SIMD is set".into());
    }
    if std::env::var_os("INVADERS_NO_AVX512").is_some() {
        return Some("INVADERS_NO_AVX512 is set".into());
    }
    #[cfg(target_arch = "x86_64")]
    {
        let missing: Vec<&str> = [
            ("avx512f", is_x86_feature_detected!("avx512f")),
            ("fma", is_x86_feature_detected!("fma")),
        ]
        .into_iter()
        .filter_map(|(name, has)| (!has).then_some(name))
        .collect();
        Some(format!("this CPU lacks {}", missing.join(" and ")))
    }
    #[cfg(not(target_arch = "x86_64"))]
    Some(format!("{} is not x86_64", std::env::consts::ARCH))
}

/// Why the AVX512-BF16 kernels do not run on this host, or `None` if they do: why the AVX-512
/// ones do not ([`why_portable`]), `INVADERS_NO_BF16`, or the missing feature.
pub fn why_no_bf16() -> Option<String> {
    if avx512_bf16() {
        return None;
    }
    why_portable().or_else(|| {
        Some(if features().bf16_switched_off {
            "INVADERS_NO_BF16 is set".into()
        } else {
            "this CPU lacks avx512bf16".into()
        })
    })
}

/// A kernel family that picks, call by call, between an AVX-512 loop, an AVX2 one where it has
/// one ([`path`]), and a portable one.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Family {
    /// The gather GEMM ([`crate::tensor::Float::gather_gemm`]).
    Gather,
    /// The scatter GEMM ([`crate::tensor::Float::scatter_gemm`]).
    Scatter,
    /// Winograd's input transform (forward pass, input gradient and weight gradient).
    WinogradInput,
    /// Winograd's output transform (forward pass, input gradient) and its adjoint (weight
    /// gradient).
    WinogradOutput,
    /// The list of an image's nonzero values ([`crate::tensor::Nonzeros::collect`]).
    Nonzeros,
    /// The sparse product ([`crate::tensor::SparseConv`]): convolutions' and dense layers'
    /// acting.
    Sparse,
    /// The scan for pixels that differ from the background ([`crate::tensor::Background::split`]).
    BackgroundSplit,
    /// The background split's product ([`crate::tensor::Background::conv`]).
    Background,
    /// [`crate::tensor::transpose`].
    Transpose,
    /// The bf16 products ([`crate::tensor::bf16`]): AVX512-BF16's `vdpbf16ps` (recorded as the
    /// AVX-512 loop), AMX's `tdpbf16ps` for the gather GEMM ([`Path::Amx`]), or the rounded
    /// operands multiplied in f32.
    Bf16,
}

const FAMILIES: usize = 10;

/// How many calls of a family ran each loop on this thread.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Paths {
    /// Calls that ran the AVX-512 loop.
    pub avx512: u64,
    /// Calls that ran the portable loop.
    pub portable: u64,
    /// Calls that ran the AVX2 loop.
    pub avx2: u64,
    /// Calls that ran on AMX tiles (the bf16 gather GEMM only).
    pub amx: u64,
}

impl Paths {
    /// The calls counted since `before` (an earlier [`paths`] of the same family and thread).
    pub fn since(self, before: Paths) -> Paths {
        Paths {
            avx512: self.avx512 - before.avx512,
            portable: self.portable - before.portable,
            avx2: self.avx2 - before.avx2,
            amx: self.amx - before.amx,
        }
    }
}

/// A loop a kernel family ran.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Path {
    /// The AVX-512 loop.
    Avx512 = 0,
    /// The portable loop.
    Portable = 1,
    /// The AVX2 and FMA loop.
    Avx2 = 2,
    /// AMX's tiles (the bf16 gather GEMM; [`bf16_gather_path`]). [`path`] never returns it.
    Amx = 3,
}

/// The loop a family with AVX-512, AVX2 and portable loops runs here.
pub fn path() -> Path {
    match (avx512(), avx2()) {
        (true, _) => Path::Avx512,
        (false, true) => Path::Avx2,
        (false, false) => Path::Portable,
    }
}

/// The loop the bf16 gather GEMM runs here: AMX's tiles ([`amx`]), else AVX512-BF16's
/// `vdpbf16ps` (recorded as the AVX-512 loop; [`avx512_bf16`]), else its portable one.
pub fn bf16_gather_path() -> Path {
    match (amx(), avx512_bf16()) {
        (true, _) => Path::Amx,
        (false, true) => Path::Avx512,
        (false, false) => Path::Portable,
    }
}

thread_local! {
    static TAKEN: [[Cell<u64>; 4]; FAMILIES] = const { [const { [const { Cell::new(0) }; 4] }; FAMILIES] };
}

/// Records that a call of `family` runs its AVX-512 loop (`avx512`) or its portable one, on
/// this thread, and returns `avx512`: the kernels branch on what this returns, so the record
/// cannot disagree with what ran.
#[inline]
pub fn took(family: Family, avx512: bool) -> bool {
    let p = if avx512 { Path::Avx512 } else { Path::Portable };
    took_path(family, p) == Path::Avx512
}

/// [`took`] for a family with an AVX2 loop as well: records `path` and returns it.
#[inline]
pub fn took_path(family: Family, path: Path) -> Path {
    TAKEN.with(|t| {
        let c = &t[family as usize][path as usize];
        c.set(c.get() + 1);
    });
    path
}

/// How many calls of `family` ran each loop on this thread so far.
pub fn paths(family: Family) -> Paths {
    TAKEN.with(|t| {
        let [a, p, v, m] = &t[family as usize];
        Paths {
            avx512: a.get(),
            portable: p.get(),
            avx2: v.get(),
            amx: m.get(),
        }
    })
}

/// Defines a function whose body is compiled for AVX-512 where [`avx512`] holds, else as built:
/// [`vectorized`] for a loop that must be a function of its own (a closure handed to
/// `vectorized` is not always inlined into it, and then runs 4 lanes wide).
///
/// ```ignore
/// avx512_twin! {
///     /// The largest offset.
///     fn largest(v: &[usize]) -> usize { v.iter().fold(0, |m, &x| m.max(x)) }
/// }
/// ```
macro_rules! avx512_twin {
    (
        $(#[$meta:meta])*
        $vis:vis fn $name:ident $(<$t:ident: $bound:path>)? ($($arg:ident: $ty:ty),* $(,)?)
            $(-> $ret:ty)? $body:block
    ) => {
        $(#[$meta])*
        $vis fn $name $(<$t: $bound>)? ($($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            fn body $(<$t: $bound>)? ($($arg: $ty),*) $(-> $ret)? $body
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f")]
                unsafe fn wide $(<$t: $bound>)? ($($arg: $ty),*) $(-> $ret)? {
                    body($($arg),*)
                }
                if $crate::tensor::cpu::avx512() {
                    // SAFETY: `avx512` checked that this CPU runs AVX-512F.
                    return unsafe { wide($($arg),*) };
                }
            }
            body($($arg),*)
        }
    };
}
pub(crate) use avx512_twin;

/// Runs `f` compiled for AVX-512 where [`avx512`] holds, else as built (baseline x86-64: 4-wide
/// SSE). The one place that enters AVX-512 code from portable code for a plain loop.
///
/// For the element-wise loops between the products (Adam, the ReLU masks,
/// the offset-table checks): they are written as plain loops, and inlined here LLVM vectorises
/// them 16 lanes wide. Each element gets the same operations in the same order either way (no
/// reassociation, no fused multiply-add), so the result is bit-identical with or without it.
#[inline(always)]
pub fn vectorized<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx512f")]
        unsafe fn wide<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        if avx512() {
            // SAFETY: `avx512` checked that this CPU runs AVX-512F.
            return unsafe { wide(f) };
        }
    }
    f()
}

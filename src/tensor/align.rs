//! Cache-line-aligned heap memory for every buffer of a program that opts in.
//!
//! The kernels move data in 64-byte AVX-512 vectors. The system allocator returns large blocks
//! 16 bytes past a page (glibc's chunk header), so every vector of a tensor, a weight matrix or
//! a scratch buffer straddled two cache lines: each load or store touched two lines, and a
//! store that splits costs two. This allocator starts every block of at least 1 KiB on a
//! 64-byte line (small ones, strings and the like, keep the system's), so every `Vec<f32>` the
//! kernels stream over starts on a cache line and its vectors lie inside lines. It takes a line
//! more from the system's `malloc` or `calloc` and hands out the first line boundary inside, so
//! a large zeroed block (`vec![0; n]`) stays untouched, and not resident, until written.
//!
//! The library does not set the program's allocator: a program that links `invaders` keeps its
//! own. The `invaders` binary, the benchmarks and the examples opt in, each with
//!
//! ```ignore
//! #[global_allocator]
//! static GLOBAL: invaders::CacheAligned = invaders::CacheAligned;
//! ```
//!
//! Without it everything computes the same values (the kernels use unaligned loads and stores
//! and assume no alignment), only slower where a vector straddles two cache lines.

use std::alloc::{GlobalAlloc, Layout, System};

/// The system allocator with blocks of 1 KiB or more aligned to 64 bytes.
pub struct CacheAligned;

/// Blocks from this size up are cache-line aligned.
const LARGE: usize = 1024;

/// The alignment given to large blocks: a cache line, an AVX-512 vector.
const LINE: usize = 64;

/// Whether `layout` is a large block this allocator aligns itself (larger alignments the
/// system gives as asked).
#[inline]
fn is_large(layout: Layout) -> bool {
    layout.size() >= LARGE && layout.align() < LINE
}

/// The block asked of the system for a large `layout`: a line more, at the system's own
/// alignment, so that a line-aligned start with the system's pointer stored just before it fits.
///
/// Why not the system's aligned allocation: for alignments above 16 bytes Rust's `System` has
/// no zeroing `calloc` and zeroes the block itself, touching every page of it. A
/// `vec![0; n]` of 7 GB (a million-entry replay memory) was then resident in full from the
/// start, and a resume, which builds one memory and loads another, needed twice that. `calloc`
/// of a large block maps fresh zero pages that cost memory only once written.
/// `None` where the size with the extra line is too large for any layout: the allocation fails.
#[inline]
fn outer(layout: Layout) -> Option<Layout> {
    Layout::from_size_align(layout.size().checked_add(LINE)?, 8).ok()
}

/// The line-aligned block inside the system's block `raw` of [`outer`]'s layout, with `raw`
/// stored in the word before it (between 8 and 64 bytes past `raw`).
///
/// # Safety
/// `raw` is null or a block of `outer(layout)` for some large `layout`.
#[inline]
unsafe fn inner(raw: *mut u8) -> *mut u8 {
    if raw.is_null() {
        return raw;
    }
    // The first line boundary at least a word past `raw`: `raw` is 8-aligned (the layout's
    // alignment), so `skip` is one of 8, 16, ..., 64 and the block's end stays inside.
    let skip = 8 + (LINE - (raw as usize + 8) % LINE) % LINE;
    let ptr = raw.add(skip);
    (ptr as *mut *mut u8).sub(1).write_unaligned(raw);
    ptr
}

// SAFETY: small blocks (and those asking 64-byte alignment or more) forward to `System` with
// their own layout. A large block is a `System` block of `outer(layout)` (which `inner` stays
// inside: the user's `size` bytes start at most 64 bytes in, the block is `size + 64` long) whose
// address is stored just before the pointer handed out; `dealloc` reads it back and frees that
// block with the same `outer(layout)`, `is_large` being a function of the layout alone.
unsafe impl GlobalAlloc for CacheAligned {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        match (is_large(layout), outer(layout)) {
            (false, _) => System.alloc(layout),
            (true, Some(o)) => inner(System.alloc(o)),
            (true, None) => std::ptr::null_mut(),
        }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        match (is_large(layout), outer(layout)) {
            (false, _) => System.alloc_zeroed(layout),
            (true, Some(o)) => inner(System.alloc_zeroed(o)),
            (true, None) => std::ptr::null_mut(),
        }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        match (is_large(layout), outer(layout)) {
            (true, Some(o)) => {
                let raw = (ptr as *mut *mut u8).sub(1).read_unaligned();
                System.dealloc(raw, o)
            }
            // A large layout without an outer one was never allocated here.
            _ => System.dealloc(ptr, layout),
        }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let new = Layout::from_size_align(new_size, layout.align()).expect("valid layout");
        if !is_large(layout) && !is_large(new) {
            // Small before and after: the system's own realloc.
            return System.realloc(ptr, layout, new_size);
        }
        // Otherwise a fresh aligned block and a copy (buffers here are sized once and reused).
        let fresh = self.alloc(new);
        if !fresh.is_null() {
            std::ptr::copy_nonoverlapping(ptr, fresh, layout.size().min(new_size));
            self.dealloc(ptr, layout);
        }
        fresh
    }
}

/// The library's own unit tests run with it, as the binaries do.
#[cfg(test)]
#[global_allocator]
static GLOBAL: CacheAligned = CacheAligned;

#[cfg(test)]
mod tests {
    /// Buffers of 1 KiB or more start on a cache line, also after growing from small ones (the
    /// `realloc` path), and keep their contents.
    #[test]
    fn large_buffers_are_cache_aligned() {
        for n in [256usize, 1000, 8192, 100_000, 1_000_000] {
            let v = vec![1.5f32; n];
            assert_eq!(v.as_ptr() as usize % 64, 0, "vec of {n}");
            let w: Vec<f64> = Vec::with_capacity(n);
            assert_eq!(w.as_ptr() as usize % 64, 0, "capacity {n}");
        }
        let mut grown = Vec::new();
        for i in 0..50_000u32 {
            grown.push(i as f32);
            if grown.capacity() * 4 >= super::LARGE {
                assert_eq!(grown.as_ptr() as usize % 64, 0, "grown to {}", grown.len());
            }
        }
        assert!(grown.iter().enumerate().all(|(i, &v)| v == i as f32));
        let mut shrunk = grown;
        shrunk.truncate(10);
        shrunk.shrink_to_fit();
        assert_eq!(shrunk, (0..10).map(|i| i as f32).collect::<Vec<_>>());
    }

    /// Zeroed blocks are zero and aligned; writing every byte of one and freeing it leaves the
    /// stored system pointer intact (a block that overlapped it would crash the free).
    #[test]
    fn zeroed_large_buffers_are_zero_aligned_and_whole() {
        for n in [1024usize, 1025, 1080, 4096 + 8, 200_000, 3 << 20] {
            for _ in 0..3 {
                let mut v = vec![0u8; n];
                assert_eq!(v.as_ptr() as usize % 64, 0, "zeroed vec of {n}");
                assert!(v.iter().all(|&b| b == 0), "zeroed vec of {n}");
                v.fill(0xff);
                let w = vec![0.0f32; n / 4];
                assert!(w.iter().all(|&x| x == 0.0));
                drop(v);
            }
        }
    }

    /// A large zeroed block costs memory only where it is written: a replay memory of a
    /// million entries (7 GB) is not resident before it fills (`calloc`'s fresh pages; the
    /// system's aligned path would zero, and so touch, every page).
    #[cfg(target_os = "linux")]
    #[test]
    fn zeroed_large_buffers_are_not_touched() {
        let rss_kb = || -> u64 {
            let status = std::fs::read_to_string("/proc/self/status").unwrap();
            let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
            line.split_whitespace().nth(1).unwrap().parse().unwrap()
        };
        let before = rss_kb();
        let v = vec![0u8; 2 << 30];
        let after = rss_kb();
        assert_eq!(v.as_ptr() as usize % 64, 0);
        assert_eq!((v[0], v[v.len() / 2], v[v.len() - 1]), (0, 0, 0));
        assert!(
            after.saturating_sub(before) < 512 << 10,
            "a 2 GiB zeroed vec made {} MiB resident",
            after.saturating_sub(before) >> 10
        );
    }
}

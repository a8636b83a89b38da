//! Random shifts' one operation (the replay memory's documentation, "Random shifts"): a frame
//! moved by whole pixels, its border repeated.

use crate::env::{FRAME_HEIGHT, FRAME_LEN, FRAME_WIDTH};

/// One 88x80 frame moved by `(dy, dx)` pixels with its border repeated: `to[y, x] =
/// frame[clamp(y + dy), clamp(x + dx)]`, the rows and columns clamped into the frame.
pub fn shift_frame(frame: &[u8], dy: i64, dx: i64, to: &mut [u8]) {
    let h = FRAME_HEIGHT as i64;
    assert!(
        frame.len() == FRAME_LEN && to.len() == FRAME_LEN,
        "88x80 frames"
    );
    // Columns: `d` of them repeat the edge pixel, the rest are one block of the source row.
    let d = dx.unsigned_abs().min(FRAME_WIDTH as u64 - 1) as usize;
    for (y, row) in to.chunks_exact_mut(FRAME_WIDTH).enumerate() {
        let from = (y as i64 + dy).clamp(0, h - 1) as usize * FRAME_WIDTH;
        let src = &frame[from..from + FRAME_WIDTH];
        if dx >= 0 {
            row[..FRAME_WIDTH - d].copy_from_slice(&src[d..]);
            row[FRAME_WIDTH - d..].fill(src[FRAME_WIDTH - 1]);
        } else {
            row[d..].copy_from_slice(&src[..FRAME_WIDTH - d]);
            row[..d].fill(src[0]);
        }
    }
}

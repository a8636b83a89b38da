//! The article's preprocessing: crop, downsample, greyscale, and (at the network input) normalise.
//!
//! The Atari screen is 210 rows by 160 columns of RGB. The article keeps rows 25, 27, ..., 199
//! (`obs[25:201:2]`, which drops the score bar at the top and the ground at the bottom and halves
//! the height) and every second column (`obs[:, ::2]`), giving an 88 x 80 image, then averages the
//! three colour channels into one grey value. Picking one pixel of each 2 x 2 block loses the
//! one-pixel-wide shots in odd columns; [`Downsample::Max`] keeps them (the `strong` preset).
//!
//! Frames stay `u8` (7 040 bytes each) so a replay memory of a million frames fits in memory;
//! they become `f32` only when written into the network's input, by [`normalize_into`].

use serde::{Deserialize, Serialize};

use super::ale::{SCREEN_HEIGHT, SCREEN_RGB_LEN, SCREEN_WIDTH};

/// Rows of a preprocessed frame.
pub const FRAME_HEIGHT: usize = 88;
/// Columns of a preprocessed frame.
pub const FRAME_WIDTH: usize = 80;
/// Pixels (= bytes) of a preprocessed frame.
pub const FRAME_LEN: usize = FRAME_HEIGHT * FRAME_WIDTH;
/// First screen row kept by the article's crop ([`Crop::Article`]).
pub const CROP_TOP: usize = 25;
/// First screen row of the mothership's band, which [`Crop::Mothership`] keeps.
pub const MOTHERSHIP_TOP: usize = 12;
/// Frame rows given to the mothership's band (screen rows 12 to 19) by [`Crop::Mothership`].
pub const MOTHERSHIP_ROWS: usize = 4;
/// First screen row of the playfield kept by [`Crop::Mothership`] below the mothership's band.
pub const PLAYFIELD_TOP: usize = 30;

/// The article's "contrast" colour, as a sum of R + G + B: `mspacman_color = 210 + 164 + 74`.
///
/// The article copied this step from a Ms. Pac-Man agent, where that colour is Ms. Pac-Man
/// herself. No pixel of Space Invaders has this colour, so in this game the step changes nothing
/// (the test suite checks this on real frames). It is therefore off by default.
pub const MSPACMAN_RGB_SUM: u16 = 210 + 164 + 74;

/// How each 2 x 2 block of screen pixels (rows `y, y + 1`, columns `x, x + 1`) becomes one
/// pixel of the 88 x 80 frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Downsample {
    /// The block's top-left pixel: the article's `obs[25:201:2, ::2]`. Space Invaders draws its
    /// shots one pixel wide, so every shot in an odd column is invisible to the network.
    #[default]
    Pick,
    /// The brightest grey of the block (a 2 x 2 max pool): a one-pixel shot stays visible
    /// wherever it is. Used by the `strong` preset.
    Max,
}

/// Which screen rows become the 88 rows of a frame.
///
/// Space Invaders draws the mothership (the "command alien ship", 200 points a hit, about 600
/// frames on screen in each pass) at screen rows 12 to 19, in the score's band: the game hides
/// the score while it flies. The article's crop starts at row 25, below it, so a
/// network fed that crop never sees the ship and hits it only by chance (the `strong` model:
/// 7 of 40 passes in 20 episodes, docs/strong.md "Seeing the mothership").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Crop {
    /// Screen rows 25 to 200 (`obs[25:201:2]`, the article's): the aliens, the shields, the
    /// cannon and the top of the ground; not the mothership.
    #[default]
    Article,
    /// Screen rows 12 to 19 (the mothership's band) as frame rows 0 to 3, then rows 30 to 197
    /// as frame rows 4 to 87: the article's crop less rows 25 to 29 (empty: the first wave's
    /// aliens start at row 31, and later waves lower) and 198 to 200 (ground), so that the ship
    /// fits in the same 88 rows. The frame, the network and their cost are unchanged. Rows 20 to
    /// 29, between the ship and the aliens, are left out; only a shot crosses them.
    Mothership,
}

impl Crop {
    /// The screen row whose block (rows `y` and `y + 1`) becomes frame row `r` (`r < 88`).
    pub fn screen_row(self, r: usize) -> usize {
        match self {
            Crop::Article => CROP_TOP + 2 * r,
            Crop::Mothership if r < MOTHERSHIP_ROWS => MOTHERSHIP_TOP + 2 * r,
            Crop::Mothership => PLAYFIELD_TOP + 2 * (r - MOTHERSHIP_ROWS),
        }
    }
}

/// The mothership's colour, RGB.
pub const MOTHERSHIP_RGB: [u8; 3] = [151, 25, 122];

/// Whether an RGB screen shows the mothership: a pixel of its colour in screen rows 12 to 19.
///
/// # Panics
/// If `rgb.len() != 210 * 160 * 3`.
pub fn mothership_on_screen(rgb: &[u8]) -> bool {
    assert_eq!(rgb.len(), SCREEN_RGB_LEN, "RGB screen has the wrong length");
    let band = MOTHERSHIP_TOP * SCREEN_WIDTH * 3
        ..(MOTHERSHIP_TOP + 2 * MOTHERSHIP_ROWS) * SCREEN_WIDTH * 3;
    rgb[band].chunks_exact(3).any(|p| p == MOTHERSHIP_RGB)
}

/// Crops, downsamples and greys one RGB screen into an 88 x 80 frame.
///
/// Output pixel `(r, c)` comes from screen rows `y = crop.screen_row(r)` (and `y + 1`; for the
/// article's crop `y = 25 + 2r`) and columns `2c` (and `2c + 1`), as [`Downsample`] says. Grey is the integer mean of the three channels
/// rounded down, `(r + g + b) / 3`. The article's code takes the floating-point mean; flooring
/// differs from it by less than one grey level.
///
/// `contrast`: if `Some(sum)`, pixels whose `r + g + b == sum` become 0 (the article's contrast
/// step, compared on the exact RGB sum as the article's float comparison effectively does),
/// before any max is taken.
///
/// # Panics
/// If `rgb.len() != 210 * 160 * 3` or `out.len() != 88 * 80`.
pub fn preprocess_rgb(
    rgb: &[u8], contrast: Option<u16>, crop: Crop, downsample: Downsample, out: &mut [u8],
) {
    assert_eq!(rgb.len(), SCREEN_RGB_LEN, "RGB screen has the wrong length");
    assert_eq!(out.len(), FRAME_LEN, "frame buffer has the wrong length");
    let key = contrast.map(u32::from).unwrap_or(u32::MAX);
    let grey = |px: &[u8]| {
        let sum = px[0] as u32 + px[1] as u32 + px[2] as u32;
        if sum == key {
            0
        } else {
            (sum / 3) as u8
        }
    };
    let screen_row = |y: usize| &rgb[y * SCREEN_WIDTH * 3..(y + 1) * SCREEN_WIDTH * 3];
    for (r, out_row) in out.chunks_exact_mut(FRAME_WIDTH).enumerate() {
        let y = crop.screen_row(r);
        debug_assert!(y + 1 < SCREEN_HEIGHT);
        let top = screen_row(y);
        match downsample {
            // Every second pixel: a stride of 6 bytes.
            Downsample::Pick => {
                for (o, px) in out_row.iter_mut().zip(top.chunks_exact(6)) {
                    *o = grey(px);
                }
            }
            Downsample::Max => {
                let bottom = screen_row(y + 1);
                for ((o, a), b) in out_row
                    .iter_mut()
                    .zip(top.chunks_exact(6))
                    .zip(bottom.chunks_exact(6))
                {
                    *o = grey(&a[..3])
                        .max(grey(&a[3..]))
                        .max(grey(&b[..3]))
                        .max(grey(&b[3..]));
                }
            }
        }
    }
}

/// Element-wise maximum of two frames into `out` (DeepMind's max over the last two raw frames,
/// which removes the flicker of sprites drawn only on every other frame).
///
/// # Panics
/// If the lengths differ.
pub fn max_into(a: &[u8], b: &[u8], out: &mut [u8]) {
    assert!(
        a.len() == b.len() && b.len() == out.len(),
        "frame lengths differ"
    );
    for ((o, &x), &y) in out.iter_mut().zip(a).zip(b) {
        *o = x.max(y);
    }
}

/// How a grey value `x` in 0..=255 becomes the network's input.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Normalization {
    /// `x / 128 - 1`, in [-1, 1): what the article says it does ("from -1 to +1").
    #[default]
    Symmetric,
    /// `(x - 128) / 128 - 1`, in [-2, 0): what the article's notebook code actually computes.
    ArticleCode,
}

impl Normalization {
    /// The normalised value of one grey level.
    pub fn apply(self, x: u8) -> f32 {
        let x = x as f32;
        match self {
            Normalization::Symmetric => x / 128.0 - 1.0,
            Normalization::ArticleCode => (x - 128.0) / 128.0 - 1.0,
        }
    }

    /// A 256-entry lookup table: `table[x] == self.apply(x)`.
    pub fn table(self) -> [f32; 256] {
        std::array::from_fn(|x| self.apply(x as u8))
    }
}

/// Writes `table[src[i]]` into `dst[i]` (use [`Normalization::table`] for `table`).
///
/// # Panics
/// If the lengths differ.
pub fn normalize_into(table: &[f32; 256], src: &[u8], dst: &mut [f32]) {
    assert_eq!(
        src.len(),
        dst.len(),
        "source and destination lengths differ"
    );
    for (d, &s) in dst.iter_mut().zip(src) {
        *d = table[s as usize];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crop_picks_the_article_rows_and_columns() {
        // Encode the row (then the column) in every pixel so we can see which ones were picked.
        let mut by_row = vec![0u8; SCREEN_RGB_LEN];
        let mut by_col = vec![0u8; SCREEN_RGB_LEN];
        for y in 0..SCREEN_HEIGHT {
            for x in 0..SCREEN_WIDTH {
                let i = (y * SCREEN_WIDTH + x) * 3;
                by_row[i..i + 3].fill(y as u8);
                by_col[i..i + 3].fill(x as u8);
            }
        }
        let mut out = vec![0u8; FRAME_LEN];
        preprocess_rgb(&by_row, None, Crop::Article, Downsample::Pick, &mut out);
        for r in 0..FRAME_HEIGHT {
            assert!(out[r * FRAME_WIDTH..(r + 1) * FRAME_WIDTH]
                .iter()
                .all(|&v| v as usize == 25 + 2 * r));
        }
        preprocess_rgb(&by_col, None, Crop::Article, Downsample::Pick, &mut out);
        for (c, &v) in out[..FRAME_WIDTH].iter().enumerate() {
            assert_eq!(v as usize, 2 * c);
        }
    }

    /// The mothership's crop: frame rows 0 to 3 are screen rows 12, 14, 16, 18 (the ship's
    /// band), rows 4 to 87 are screen rows 30, 32, ..., 196; with the max, each block's second
    /// row (13, ..., 197) counts too. Screen rows 20 to 29 and 198 onwards never reach a frame.
    #[test]
    fn the_mothership_crop_keeps_the_ship_band_and_the_playfield() {
        let mut by_row = vec![0u8; SCREEN_RGB_LEN];
        for y in 0..SCREEN_HEIGHT {
            by_row[y * SCREEN_WIDTH * 3..(y + 1) * SCREEN_WIDTH * 3].fill(y as u8);
        }
        let mut out = vec![0u8; FRAME_LEN];
        let row = |out: &[u8], r: usize| {
            let px = &out[r * FRAME_WIDTH..(r + 1) * FRAME_WIDTH];
            assert!(px.iter().all(|&v| v == px[0]));
            px[0] as usize
        };
        preprocess_rgb(&by_row, None, Crop::Mothership, Downsample::Pick, &mut out);
        let picked: Vec<usize> = (0..FRAME_HEIGHT).map(|r| row(&out, r)).collect();
        assert_eq!(&picked[..5], &[12, 14, 16, 18, 30]);
        assert_eq!(picked[FRAME_HEIGHT - 1], 196);
        assert!(picked.windows(2).skip(4).all(|w| w[1] == w[0] + 2));
        preprocess_rgb(&by_row, None, Crop::Mothership, Downsample::Max, &mut out);
        let maxed: Vec<usize> = (0..FRAME_HEIGHT).map(|r| row(&out, r)).collect();
        assert_eq!(&maxed[..5], &[13, 15, 17, 19, 31]);
        assert_eq!(maxed[FRAME_HEIGHT - 1], 197);
        // The article's crop, for comparison: rows 25 to 200, nothing above.
        preprocess_rgb(&by_row, None, Crop::Article, Downsample::Max, &mut out);
        assert_eq!((row(&out, 0), row(&out, FRAME_HEIGHT - 1)), (26, 200));
        for r in 0..FRAME_HEIGHT {
            assert_eq!(Crop::Article.screen_row(r), CROP_TOP + 2 * r);
        }
    }

    #[test]
    fn grey_is_floor_of_mean_and_contrast_matches_exact_sum() {
        let mut rgb = vec![0u8; SCREEN_RGB_LEN];
        let i = (CROP_TOP * SCREEN_WIDTH + 2) * 3; // second output pixel of the first row
        rgb[i..i + 3].copy_from_slice(&[1, 1, 2]); // sum 4 -> 1
        let j = (CROP_TOP * SCREEN_WIDTH + 4) * 3;
        rgb[j..j + 3].copy_from_slice(&[210, 164, 74]); // the Ms. Pac-Man colour
        let k = (CROP_TOP * SCREEN_WIDTH + 6) * 3;
        rgb[k..k + 3].copy_from_slice(&[210, 164, 75]); // one off
        let mut out = vec![0u8; FRAME_LEN];
        preprocess_rgb(&rgb, None, Crop::Article, Downsample::Pick, &mut out);
        assert_eq!(&out[..4], &[0, 1, 149, 149]);
        preprocess_rgb(
            &rgb,
            Some(MSPACMAN_RGB_SUM),
            Crop::Article,
            Downsample::Pick,
            &mut out,
        );
        assert_eq!(&out[..4], &[0, 1, 0, 149]);
    }

    /// A one-pixel shot in an odd column (x = 47) and odd row vanishes when the top-left pixel
    /// of each block is picked and survives the max, at its block (row 0, column 23).
    #[test]
    fn max_keeps_a_one_pixel_shot_that_pick_loses() {
        let mut rgb = vec![0u8; SCREEN_RGB_LEN];
        let shot = |y: usize| ((y * SCREEN_WIDTH) + 47) * 3;
        let i = shot(CROP_TOP + 1);
        rgb[i..i + 3].copy_from_slice(&[142, 142, 142]);
        let j = (CROP_TOP * SCREEN_WIDTH + 46) * 3; // the block's top-left pixel, dimmer
        rgb[j..j + 3].copy_from_slice(&[30, 30, 30]);
        let mut out = vec![0u8; FRAME_LEN];
        preprocess_rgb(&rgb, None, Crop::Article, Downsample::Pick, &mut out);
        assert_eq!(out[23], 30);
        assert_eq!(out.iter().map(|&v| v as u32).sum::<u32>(), 30);
        preprocess_rgb(&rgb, None, Crop::Article, Downsample::Max, &mut out);
        assert_eq!(out[23], 142);
        assert_eq!(out.iter().map(|&v| v as u32).sum::<u32>(), 142);
        // The contrast colour is blanked before the max: it cannot win a block.
        rgb[i..i + 3].copy_from_slice(&[210, 164, 74]);
        preprocess_rgb(
            &rgb,
            Some(MSPACMAN_RGB_SUM),
            Crop::Article,
            Downsample::Max,
            &mut out,
        );
        assert_eq!(out[23], 30);
    }

    #[test]
    fn normalisations_have_the_stated_ranges() {
        let s = Normalization::Symmetric.table();
        assert_eq!((s[0], s[128], s[255]), (-1.0, 0.0, 255.0 / 128.0 - 1.0));
        let a = Normalization::ArticleCode.table();
        assert_eq!((a[0], a[128], a[255]), (-2.0, -1.0, 127.0 / 128.0 - 1.0));
        let mut dst = [0.0f32; 3];
        normalize_into(&s, &[0, 128, 64], &mut dst);
        assert_eq!(dst, [-1.0, 0.0, -0.5]);
    }
}

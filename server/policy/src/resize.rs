//! openpi's `image_tools.resize_with_pad` (openpi-client 0.1.2): Pillow's bilinear `Image.resize` to the
//! largest size that fits, pasted centred onto black. The resampler is Pillow's (`libImaging/Resample.c`,
//! Pillow 10.4): a triangle filter stretched by the scale when shrinking (so it averages, unlike a
//! textbook bilinear sample), separable, horizontal pass first, with 22-bit fixed-point weights for 8-bit
//! images. Ported to the integer so that our input is the policy's training input bit for bit; the tests
//! compare it with Pillow itself.

/// Pillow's `PRECISION_BITS` for 8-bit images.
const PRECISION_BITS: u32 = 32 - 8 - 2;

/// An 8-bit interleaved image, rows top first.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Image8 {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    pub data: Vec<u8>,
}

/// The taps of each output pixel along one axis: first input index, count, fixed-point weights.
struct Taps {
    first: Vec<usize>,
    count: Vec<usize>,
    weights: Vec<i32>,
    ksize: usize,
}

fn bilinear_filter(x: f64) -> f64 {
    let x = x.abs();
    if x < 1.0 { 1.0 - x } else { 0.0 }
}

/// Pillow's `precompute_coeffs` and `normalize_coeffs_8bpc` for the box `[0, in_size)`.
fn taps(in_size: usize, out_size: usize) -> Taps {
    let scale = in_size as f64 / out_size as f64;
    let filterscale = scale.max(1.0);
    let support = filterscale; // the bilinear filter's support is 1
    let ksize = support.ceil() as usize * 2 + 1;
    let mut taps = Taps { first: Vec::with_capacity(out_size), count: Vec::with_capacity(out_size), weights: vec![0; out_size * ksize], ksize };
    let ss = 1.0 / filterscale;
    for xx in 0..out_size {
        let center = (xx as f64 + 0.5) * scale;
        // C's `(int)` truncates toward zero, as `as i64` does.
        let xmin = ((center - support + 0.5) as i64).max(0) as usize;
        let xmax = ((center + support + 0.5) as i64).min(in_size as i64) as usize;
        let n = xmax.saturating_sub(xmin);
        let k: Vec<f64> = (0..n).map(|x| bilinear_filter((x as f64 + xmin as f64 - center + 0.5) * ss)).collect();
        let ww: f64 = k.iter().sum();
        for (x, w) in k.iter().enumerate() {
            let w = if ww != 0.0 { w / ww } else { *w };
            let fixed = w * f64::from(1u32 << PRECISION_BITS);
            taps.weights[xx * ksize + x] = if w < 0.0 { (-0.5 + fixed) as i32 } else { (0.5 + fixed) as i32 };
        }
        taps.first.push(xmin);
        taps.count.push(n);
    }
    taps
}

fn clip8(sum: i32) -> u8 {
    (sum >> PRECISION_BITS).clamp(0, 255) as u8
}

/// Pillow's `Image.resize((out_w, out_h), Image.BILINEAR)` of an 8-bit image.
pub fn resize_bilinear(img: &Image8, out_w: usize, out_h: usize) -> Image8 {
    let c = img.channels;
    let half = 1i32 << (PRECISION_BITS - 1);
    if (out_w, out_h) == (img.width, img.height) {
        return img.clone();
    }
    // Horizontal pass (skipped, as Pillow skips it, when the width stays).
    let horizontal = if out_w != img.width {
        let t = taps(img.width, out_w);
        let mut out = vec![0u8; out_w * img.height * c];
        for y in 0..img.height {
            let row = &img.data[y * img.width * c..(y + 1) * img.width * c];
            for xx in 0..out_w {
                let k = &t.weights[xx * t.ksize..xx * t.ksize + t.count[xx]];
                for ch in 0..c {
                    let mut ss = half;
                    for (i, w) in k.iter().enumerate() {
                        ss += i32::from(row[(t.first[xx] + i) * c + ch]) * w;
                    }
                    out[(y * out_w + xx) * c + ch] = clip8(ss);
                }
            }
        }
        Image8 { width: out_w, height: img.height, channels: c, data: out }
    } else {
        img.clone()
    };
    if out_h == img.height {
        return horizontal;
    }
    let t = taps(img.height, out_h);
    let w = horizontal.width;
    let mut out = vec![0u8; w * out_h * c];
    for yy in 0..out_h {
        let k = &t.weights[yy * t.ksize..yy * t.ksize + t.count[yy]];
        for x in 0..w {
            for ch in 0..c {
                let mut ss = half;
                for (i, wt) in k.iter().enumerate() {
                    ss += i32::from(horizontal.data[((t.first[yy] + i) * w + x) * c + ch]) * wt;
                }
                out[(yy * w + x) * c + ch] = clip8(ss);
            }
        }
    }
    Image8 { width: w, height: out_h, channels: c, data: out }
}

/// openpi's `resize_with_pad(img, height, width)`: unchanged when already that size, else the
/// aspect-preserving bilinear resize pasted at `(int((width - w) / 2), int((height - h) / 2))` on black.
pub fn resize_with_pad(img: &Image8, height: usize, width: usize) -> Image8 {
    if (img.width, img.height) == (width, height) {
        return img.clone();
    }
    let ratio = (img.width as f64 / width as f64).max(img.height as f64 / height as f64);
    let rh = (img.height as f64 / ratio) as usize;
    let rw = (img.width as f64 / ratio) as usize;
    let resized = resize_bilinear(img, rw, rh);
    let c = img.channels;
    let pad_h = (height.saturating_sub(rh)) / 2;
    let pad_w = (width.saturating_sub(rw)) / 2;
    let mut out = vec![0u8; width * height * c];
    for y in 0..rh.min(height) {
        let src = &resized.data[y * rw * c..(y * rw + rw.min(width)) * c];
        let dst = ((y + pad_h) * width + pad_w) * c;
        out[dst..dst + src.len()].copy_from_slice(src);
    }
    Image8 { width, height, channels: c, data: out }
}

/// `img[::-1, ::-1]`: the 180° rotation.
pub fn rotate_180(img: &Image8) -> Image8 {
    let c = img.channels;
    let mut out = Vec::with_capacity(img.data.len());
    for px in img.data.chunks_exact(c).rev() {
        out.extend_from_slice(px);
    }
    Image8 { data: out, ..img.clone() }
}

/// `img[:, ::-1]`: the left-right mirror.
pub fn mirror_left_right(img: &Image8) -> Image8 {
    let c = img.channels;
    let mut out = Vec::with_capacity(img.data.len());
    for row in img.data.chunks_exact(img.width * c) {
        for px in row.chunks_exact(c).rev() {
            out.extend_from_slice(px);
        }
    }
    Image8 { data: out, ..img.clone() }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(w: usize, h: usize) -> Image8 {
        Image8 { width: w, height: h, channels: 3, data: (0..w * h * 3).map(|i| (i * 7 % 251) as u8).collect() }
    }

    #[test]
    fn a_flat_image_stays_flat() {
        let img = Image8 { width: 256, height: 256, channels: 3, data: vec![200; 256 * 256 * 3] };
        assert!(resize_bilinear(&img, 224, 224).data.iter().all(|&v| v == 200));
    }

    #[test]
    fn mirror_then_flip_rows_is_the_rotation() {
        let img = ramp(5, 3);
        let flipped_rows: Vec<u8> = img.data.chunks_exact(15).rev().flatten().copied().collect();
        let flipped = Image8 { data: flipped_rows, ..img.clone() };
        assert_eq!(mirror_left_right(&flipped), rotate_180(&img));
    }

    #[test]
    fn a_wide_image_is_padded_top_and_bottom() {
        let out = resize_with_pad(&ramp(40, 20), 10, 10);
        assert_eq!((out.width, out.height), (10, 10));
        // 40×20 → 10×5 at row offset 2: rows 0–1 and 7–9 are black.
        assert!(out.data[..2 * 10 * 3].iter().all(|&v| v == 0));
        assert!(out.data[7 * 10 * 3..].iter().all(|&v| v == 0));
    }
}

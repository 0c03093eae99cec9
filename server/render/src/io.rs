//! Writers for the renderer's outputs: PNG (RGB, 8-bit grey, 16-bit segmentation ids) and NumPy `.npy`.
use std::io::Write;
use std::path::Path;

use crate::RenderError;

fn png_bytes(width: u32, height: u32, color: png::ColorType, depth: png::BitDepth, data: &[u8]) -> Result<Vec<u8>, RenderError> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, width, height);
        enc.set_color(color);
        enc.set_depth(depth);
        let mut w = enc.write_header().map_err(|e| RenderError::Encode(e.to_string()))?;
        w.write_image_data(data).map_err(|e| RenderError::Encode(e.to_string()))?;
    }
    Ok(out)
}

/// RGB8, row-major, top row first.
pub fn encode_rgb_png(width: u32, height: u32, rgb: &[u8]) -> Result<Vec<u8>, RenderError> {
    png_bytes(width, height, png::ColorType::Rgb, png::BitDepth::Eight, rgb)
}

/// 8-bit greyscale.
pub fn encode_gray_png(width: u32, height: u32, gray: &[u8]) -> Result<Vec<u8>, RenderError> {
    png_bytes(width, height, png::ColorType::Grayscale, png::BitDepth::Eight, gray)
}

/// Segmentation ids as 16-bit greyscale (big-endian per PNG); site ids keep bit 15 as their flag.
pub fn encode_segmentation_png(width: u32, height: u32, seg: &[u32]) -> Result<Vec<u8>, RenderError> {
    let mut data = Vec::with_capacity(seg.len() * 2);
    for &s in seg {
        let v: u16 = if s & crate::SEG_SITE_FLAG != 0 { 0x8000 | (s & 0x7fff) as u16 } else { s.min(0x7fff) as u16 };
        data.extend_from_slice(&v.to_be_bytes());
    }
    png_bytes(width, height, png::ColorType::Grayscale, png::BitDepth::Sixteen, &data)
}

/// `.npy` v1.0 bytes of a C-order little-endian float32 array of shape (height, width).
pub fn npy_f32_bytes(height: u32, width: u32, values: &[f32]) -> Vec<u8> {
    let dict = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({height}, {width}), }}");
    let unpadded = 10 + dict.len() + 1;
    let pad = (64 - unpadded % 64) % 64;
    let header = format!("{dict}{}\n", " ".repeat(pad));
    let mut out = Vec::with_capacity(10 + header.len() + 4 * values.len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Write bytes to `path` atomically (temp file + rename) so readers never see half a file.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), RenderError> {
    let tmp = path.with_extension("tmp-write");
    {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
    }
    std::fs::rename(&tmp, path)?;
    Ok(())
}

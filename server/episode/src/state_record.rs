//! The per-control-step state record (`state_record.bin` in the run directory): what the private video needs to
//! draw a frame, recorded by the episode thread instead of pixels (issue 19). A frame is the `qpos` the step's
//! poses came from and the mocap poses ([`libero_sim::PoseReplay`] turns them back into exactly those poses);
//! the site and geom colours a video frame shows are the model's own, fixed for the episode.
//!
//! Layout, little-endian: a 32-byte header (`MAGIC`, `u32` nq, `u32` nmocap, `u64` zero), then one frame after
//! another, `nq + 7·nmocap` `f64` each. Every frame is one `write` to the file as it is stepped, so a server
//! killed mid-episode leaves every recorded frame on disk; a torn last frame is ignored when reading.
use std::fs::File;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use thiserror::Error;

pub const STATE_RECORD_FILE: &str = "state_record.bin";
const MAGIC: &[u8; 16] = b"LIBERO-STATE-v1\0";
const HEADER_BYTES: usize = 32;
/// Far above any MuJoCo scene here (LIBERO scenes have about 100 `qpos`), so a damaged header is refused.
const MAX_VALUES_PER_FRAME: usize = 1 << 16;

#[derive(Debug, Error)]
pub enum StateRecordError {
    #[error("state record {path}: {message}")]
    Format { path: PathBuf, message: String },
    #[error("state record {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StateRecordError + '_ {
    move |source| StateRecordError::Io { path: path.to_owned(), source }
}

/// Appends frames as the episode steps.
#[derive(Debug)]
pub struct StateRecordWriter {
    path: PathBuf,
    file: File,
    nq: usize,
    nmocap: usize,
    frames: u64,
    buf: Vec<u8>,
}

impl StateRecordWriter {
    /// Creates the record (an existing file of that name is an error: records are never overwritten).
    pub fn create(path: &Path, nq: usize, nmocap: usize) -> Result<Self, StateRecordError> {
        if nq + 7 * nmocap > MAX_VALUES_PER_FRAME {
            return Err(StateRecordError::Format { path: path.to_owned(), message: format!("{nq} qpos and {nmocap} mocap bodies") });
        }
        let mut file = std::fs::OpenOptions::new().write(true).create_new(true).open(path).map_err(io(path))?;
        let mut header = Vec::with_capacity(HEADER_BYTES);
        header.extend_from_slice(MAGIC);
        header.extend_from_slice(&(nq as u32).to_le_bytes());
        header.extend_from_slice(&(nmocap as u32).to_le_bytes());
        header.extend_from_slice(&0u64.to_le_bytes());
        file.write_all(&header).map_err(io(path))?;
        Ok(Self { path: path.to_owned(), file, nq, nmocap, frames: 0, buf: Vec::new() })
    }

    /// Appends one frame (one `write`).
    pub fn push(&mut self, qpos: &[f64], mocap: &[f64]) -> Result<(), StateRecordError> {
        if qpos.len() != self.nq || mocap.len() != 7 * self.nmocap {
            return Err(StateRecordError::Format {
                path: self.path.clone(),
                message: format!("frame of {} qpos and {} mocap values for a record of {} and {}", qpos.len(), mocap.len(), self.nq, 7 * self.nmocap),
            });
        }
        self.buf.clear();
        for x in qpos.iter().chain(mocap) {
            self.buf.extend_from_slice(&x.to_le_bytes());
        }
        self.file.write_all(&self.buf).map_err(io(&self.path))?;
        self.frames += 1;
        Ok(())
    }

    pub fn frames(&self) -> u64 {
        self.frames
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Makes every frame durable (the episode's end).
    pub fn sync(&self) -> Result<(), StateRecordError> {
        self.file.sync_data().map_err(io(&self.path))
    }
}

/// The episode's end: every frame durable before the video is queued.
impl Drop for StateRecordWriter {
    fn drop(&mut self) {
        if let Err(e) = self.sync() {
            log::warn!("{e}");
        }
    }
}

/// Reads a record frame by frame.
#[derive(Debug)]
pub struct StateRecordReader {
    path: PathBuf,
    file: std::io::BufReader<File>,
    pub nq: usize,
    pub nmocap: usize,
    frames: u64,
    read: u64,
}

impl StateRecordReader {
    pub fn open(path: &Path) -> Result<Self, StateRecordError> {
        let file = File::open(path).map_err(io(path))?;
        let len = file.metadata().map_err(io(path))?.len();
        let mut file = std::io::BufReader::new(file);
        let mut header = [0u8; HEADER_BYTES];
        let bad = |message: String| StateRecordError::Format { path: path.to_owned(), message };
        file.read_exact(&mut header).map_err(|_| bad("shorter than its header".into()))?;
        if &header[..16] != MAGIC {
            return Err(bad("not a state record (bad magic)".into()));
        }
        let nq = u32::from_le_bytes(header[16..20].try_into().unwrap_or_default()) as usize;
        let nmocap = u32::from_le_bytes(header[20..24].try_into().unwrap_or_default()) as usize;
        let values = nq.checked_add(nmocap.saturating_mul(7)).filter(|v| (1..=MAX_VALUES_PER_FRAME).contains(v));
        let Some(values) = values else { return Err(bad(format!("{nq} qpos and {nmocap} mocap bodies"))) };
        let frames = (len - HEADER_BYTES as u64) / (values as u64 * 8);
        Ok(Self { path: path.to_owned(), file, nq, nmocap, frames, read: 0 })
    }

    /// Whole frames in the file when it was opened.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// The next frame's `(qpos, mocap)`, or `None` after the last whole frame.
    pub fn next_frame(&mut self) -> Result<Option<(Vec<f64>, Vec<f64>)>, StateRecordError> {
        if self.read >= self.frames {
            return Ok(None);
        }
        let mut bytes = vec![0u8; (self.nq + 7 * self.nmocap) * 8];
        self.file.read_exact(&mut bytes).map_err(io(&self.path))?;
        let mut values = bytes.chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().unwrap_or_default()));
        let qpos: Vec<f64> = values.by_ref().take(self.nq).collect();
        let mocap: Vec<f64> = values.collect();
        self.read += 1;
        Ok(Some((qpos, mocap)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_read_back_bit_for_bit_and_a_torn_tail_is_ignored() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(STATE_RECORD_FILE);
        let mut w = StateRecordWriter::create(&path, 3, 1).unwrap();
        let frames: Vec<(Vec<f64>, Vec<f64>)> =
            (0..5).map(|i| (vec![i as f64, -0.1 * i as f64, f64::MIN_POSITIVE], vec![0.5, 1.0, 2.0, 1.0, 0.0, 0.0, 1e-300])).collect();
        for (q, m) in &frames {
            w.push(q, m).unwrap();
        }
        assert!(w.push(&[1.0], &[]).is_err(), "a frame of the wrong size is refused");
        w.sync().unwrap();
        assert!(StateRecordWriter::create(&path, 3, 1).is_err(), "never overwritten");
        // A torn write at the end (a killed server).
        std::fs::OpenOptions::new().append(true).open(&path).unwrap().write_all(&[1, 2, 3]).unwrap();
        let mut r = StateRecordReader::open(&path).unwrap();
        assert_eq!((r.nq, r.nmocap, r.frames()), (3, 1, 5));
        for f in &frames {
            let got = r.next_frame().unwrap().unwrap();
            assert_eq!(got.0.iter().map(|x| x.to_bits()).collect::<Vec<_>>(), f.0.iter().map(|x| x.to_bits()).collect::<Vec<_>>());
            assert_eq!(got.1, f.1);
        }
        assert!(r.next_frame().unwrap().is_none());
    }

    #[test]
    fn a_foreign_or_damaged_file_is_refused_clearly() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.bin");
        std::fs::write(&path, b"not a record at all, but long enough for a header").unwrap();
        assert!(StateRecordReader::open(&path).unwrap_err().to_string().contains("bad magic"));
        let mut header = MAGIC.to_vec();
        header.extend_from_slice(&u32::MAX.to_le_bytes());
        header.extend_from_slice(&[0u8; 12]);
        std::fs::write(&path, &header).unwrap();
        assert!(StateRecordReader::open(&path).is_err());
        std::fs::write(&path, b"short").unwrap();
        assert!(StateRecordReader::open(&path).unwrap_err().to_string().contains("header"));
    }
}

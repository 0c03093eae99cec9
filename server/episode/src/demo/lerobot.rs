//! Export of library bundles to the LeRobot dataset format v3.0, so recorded demonstrations train ordinary
//! LeRobot policies. One row per transition (the observation before the action, and the action); the bundle's
//! per-camera MP4s become one video file per episode per camera (v3 locates an episode's frames by chunk, file
//! and timestamps in `meta/episodes`, so per-episode files are valid v3 and need no re-encoding).
//!
//! Written with `parquet`'s low-level column writer (no Arrow, no compression codecs): small to build, and the
//! files are plain Parquet any reader opens. Not written: per-episode `stats/*` columns and image statistics
//! (they need decoded pixels); `meta/stats.json` holds the numeric features' statistics.
use std::fs::{self, File};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{Quaternion, UnitQuaternion};
use parquet::basic::{LogicalType, Repetition, Type as PhysicalType};
use parquet::data_type::{ByteArray, ByteArrayType, DoubleType, FloatType, Int64Type};
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use parquet::file::writer::SerializedFileWriter;
use parquet::schema::types::Type;
use serde_json::{Value, json};

use super::*;
use crate::world::RESOLUTION_PX;

pub const CODEBASE_VERSION: &str = "v3.0";
/// Files per chunk directory (LeRobot's default).
pub const CHUNKS_SIZE: usize = 1000;
pub const HEAD_KEY: &str = "observation.images.head";
pub const WRIST_KEY: &str = "observation.images.wrist";
pub const STATE_NAMES: [&str; 8] =
    ["eef_x_m", "eef_y_m", "eef_z_m", "eef_axis_angle_x_rad", "eef_axis_angle_y_rad", "eef_axis_angle_z_rad", "gripper_finger_left_m", "gripper_finger_right_m"];

/// One column of a table.
pub enum Column {
    F32(Vec<f32>),
    F64(Vec<f64>),
    I64(Vec<i64>),
    Str(Vec<String>),
    /// Each row a list (fixed length in practice: the feature's shape).
    F32List(Vec<Vec<f32>>),
    StrList(Vec<Vec<String>>),
}

fn pq(e: parquet::errors::ParquetError) -> DemoError {
    DemoError::Export(e.to_string())
}

fn leaf(name: &str, physical: PhysicalType, repetition: Repetition, logical: Option<LogicalType>) -> Result<Type, DemoError> {
    Type::primitive_type_builder(name, physical).with_repetition(repetition).with_logical_type(logical).build().map_err(pq)
}

/// The standard three-level LIST: `required group <name> (LIST) { repeated group list { required <T> element } }`.
fn list_of(name: &str, element: Type) -> Result<Type, DemoError> {
    let list = Type::group_type_builder("list").with_repetition(Repetition::REPEATED).with_fields(vec![Arc::new(element)]).build().map_err(pq)?;
    Type::group_type_builder(name)
        .with_repetition(Repetition::REQUIRED)
        .with_logical_type(Some(LogicalType::List))
        .with_fields(vec![Arc::new(list)])
        .build()
        .map_err(pq)
}

fn levels<T>(rows: &[Vec<T>]) -> (Vec<i16>, Vec<i16>) {
    let mut def = Vec::new();
    let mut rep = Vec::new();
    for row in rows {
        // An empty list would need def 0 with no value; our lists are never empty.
        for k in 0..row.len() {
            def.push(1);
            rep.push(i16::from(k > 0));
        }
    }
    (def, rep)
}

/// Writes `columns` (all of the same length) as one row group.
pub fn write_table<S: AsRef<str>>(path: &Path, columns: &[(S, Column)], metadata: Vec<KeyValue>) -> Result<(), DemoError> {
    let req = Repetition::REQUIRED;
    let mut fields = Vec::new();
    for (name, col) in columns {
        let name = name.as_ref();
        let t = match col {
            Column::F32(_) => leaf(name, PhysicalType::FLOAT, req, None)?,
            Column::F64(_) => leaf(name, PhysicalType::DOUBLE, req, None)?,
            Column::I64(_) => leaf(name, PhysicalType::INT64, req, None)?,
            Column::Str(_) => leaf(name, PhysicalType::BYTE_ARRAY, req, Some(LogicalType::String))?,
            Column::F32List(_) => list_of(name, leaf("element", PhysicalType::FLOAT, req, None)?)?,
            Column::StrList(_) => list_of(name, leaf("element", PhysicalType::BYTE_ARRAY, req, Some(LogicalType::String))?)?,
        };
        fields.push(Arc::new(t));
    }
    let schema = Type::group_type_builder("schema").with_fields(fields).build().map_err(pq)?;
    let props = WriterProperties::builder().set_key_value_metadata((!metadata.is_empty()).then_some(metadata)).build();
    let file = File::create(path).map_err(io_err(path))?;
    let mut writer = SerializedFileWriter::new(file, Arc::new(schema), Arc::new(props)).map_err(pq)?;
    let mut group = writer.next_row_group().map_err(pq)?;
    for (_, col) in columns {
        let mut w = group.next_column().map_err(pq)?.ok_or_else(|| DemoError::Export("fewer parquet columns than fields".into()))?;
        match col {
            Column::F32(v) => w.typed::<FloatType>().write_batch(v, None, None).map(drop),
            Column::F64(v) => w.typed::<DoubleType>().write_batch(v, None, None).map(drop),
            Column::I64(v) => w.typed::<Int64Type>().write_batch(v, None, None).map(drop),
            Column::Str(v) => {
                let b: Vec<ByteArray> = v.iter().map(|s| ByteArray::from(s.as_str())).collect();
                w.typed::<ByteArrayType>().write_batch(&b, None, None).map(drop)
            }
            Column::F32List(rows) => {
                let (def, rep) = levels(rows);
                let flat: Vec<f32> = rows.concat();
                w.typed::<FloatType>().write_batch(&flat, Some(&def), Some(&rep)).map(drop)
            }
            Column::StrList(rows) => {
                let (def, rep) = levels(rows);
                let flat: Vec<ByteArray> = rows.iter().flatten().map(|s| ByteArray::from(s.as_str())).collect();
                w.typed::<ByteArrayType>().write_batch(&flat, Some(&def), Some(&rep)).map(drop)
            }
        }
        .map_err(pq)?;
        w.close().map_err(pq)?;
    }
    group.close().map_err(pq)?;
    writer.close().map_err(pq)?;
    Ok(())
}

/// `[x, y, z, axis-angle (3), fingers (2)]`: LIBERO's LeRobot state layout, from a measured state.
pub fn state_vector(s: &MeasuredState) -> Vec<f32> {
    let p = s.eef_pose_robot_base_xyzw;
    let q = UnitQuaternion::from_quaternion(Quaternion::new(p[6], p[3], p[4], p[5]));
    let aa = q.scaled_axis();
    let g = s.gripper_finger_joint_position_m;
    [p[0], p[1], p[2], aa[0], aa[1], aa[2], g[0], g[1]].iter().map(|x| *x as f32).collect()
}

/// `{min, max, mean, std, count}` per component (LeRobot's stats layout).
fn stats(rows: &[Vec<f64>]) -> Value {
    let n = rows.len();
    let dim = rows.first().map_or(0, Vec::len);
    let col = |k: usize| rows.iter().map(move |r| r[k]);
    let mean: Vec<f64> = (0..dim).map(|k| col(k).sum::<f64>() / n.max(1) as f64).collect();
    json!({
        "min": (0..dim).map(|k| col(k).fold(f64::INFINITY, f64::min)).collect::<Vec<_>>(),
        "max": (0..dim).map(|k| col(k).fold(f64::NEG_INFINITY, f64::max)).collect::<Vec<_>>(),
        "mean": mean,
        "std": (0..dim).map(|k| (col(k).map(|x| (x - mean[k]).powi(2)).sum::<f64>() / n.max(1) as f64).sqrt()).collect::<Vec<_>>(),
        "count": [n],
    })
}

/// What was exported.
#[derive(Debug, Clone, PartialEq)]
pub struct ExportSummary {
    pub out: PathBuf,
    pub episodes: usize,
    pub frames: usize,
    pub tasks: usize,
}

fn video_feature() -> Value {
    json!({
        "dtype": "video",
        "shape": [RESOLUTION_PX, RESOLUTION_PX, 3],
        "names": ["height", "width", "channels"],
        "info": {
            "video.height": RESOLUTION_PX, "video.width": RESOLUTION_PX, "video.codec": "h264",
            "video.pix_fmt": "yuv420p", "video.is_depth_map": false, "video.fps": DEMO_VIDEO_FPS_HZ, "video.channels": 3,
            "has_audio": false
        }
    })
}

/// Exports valid library bundles into a new LeRobot v3 dataset at `out` (which must not exist or be empty).
pub fn export_lerobot(bundles: &[PathBuf], out: &Path) -> Result<ExportSummary, DemoError> {
    if bundles.is_empty() {
        return Err(DemoError::Export("no bundles given".into()));
    }
    if out.exists() && fs::read_dir(out).map_err(io_err(out))?.next().is_some() {
        return Err(DemoError::Export(format!("{} exists and is not empty", out.display())));
    }
    let mut tasks: Vec<String> = Vec::new();
    // data columns
    let (mut state, mut action, mut timestamp) = (Vec::new(), Vec::new(), Vec::new());
    let (mut frame_index, mut episode_index, mut index, mut task_index) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    // episodes columns
    let mut ep = EpisodeColumns::default();
    for (e, dir) in bundles.iter().enumerate() {
        let violations = validate_bundle(dir);
        if !violations.is_empty() {
            return Err(DemoError::Invalid { dir: dir.clone(), violations });
        }
        let instruction = read_manifest(&dir.join(MANIFEST))?.instruction().unwrap_or_default().to_owned();
        let t = match tasks.iter().position(|x| *x == instruction) {
            Some(t) => t,
            None => {
                tasks.push(instruction.clone());
                tasks.len() - 1
            }
        };
        let path = dir.join(TRAJECTORY);
        let text = fs::read_to_string(&path).map_err(io_err(&path))?;
        let from = index.len();
        for (i, line) in text.lines().enumerate() {
            let (a, row) = read_trajectory_row(line, i + 1).map_err(|e| match e {
                DemoError::Source(why) => DemoError::Export(format!("{}: {why}", path.display())),
                other => other,
            })?;
            let s = row
                .state_before
                .as_ref()
                .and_then(MeasuredState::from_record)
                .ok_or_else(|| DemoError::Export(format!("{}: bad state_before", path.display())))?;
            state.push(state_vector(&s));
            action.push(a.iter().map(|x| *x as f32).collect::<Vec<f32>>());
            timestamp.push((i as f64 / DEMO_VIDEO_FPS_HZ) as f32);
            frame_index.push(i as i64);
            episode_index.push(e as i64);
            index.push(index.len() as i64);
            task_index.push(t as i64);
        }
        let length = index.len() - from;
        let (chunk, file) = ((e / CHUNKS_SIZE) as i64, (e % CHUNKS_SIZE) as i64);
        for (key, rel) in [(HEAD_KEY, VIDEO_HEAD), (WRIST_KEY, VIDEO_WRIST)] {
            let dest = out.join(format!("videos/{key}/chunk-{chunk:03}/file-{file:03}.mp4"));
            fs::create_dir_all(dest.parent().unwrap_or(out)).map_err(io_err(&dest))?;
            fs::copy(dir.join(rel), &dest).map_err(io_err(&dest))?;
        }
        ep.push(e, vec![instruction], length, from, chunk, file);
    }
    let data_dir = out.join("data/chunk-000");
    fs::create_dir_all(&data_dir).map_err(io_err(&data_dir))?;
    let total_frames = index.len();
    let state64: Vec<Vec<f64>> = state.iter().map(|r| r.iter().map(|x| f64::from(*x)).collect()).collect();
    let action64: Vec<Vec<f64>> = action.iter().map(|r| r.iter().map(|x| f64::from(*x)).collect()).collect();
    let scalar = |v: &[i64]| stats(&v.iter().map(|x| vec![*x as f64]).collect::<Vec<_>>());
    let stats_json = json!({
        "observation.state": stats(&state64),
        "action": stats(&action64),
        "timestamp": stats(&timestamp.iter().map(|x| vec![f64::from(*x)]).collect::<Vec<_>>()),
        "frame_index": scalar(&frame_index),
        "episode_index": scalar(&episode_index),
        "index": scalar(&index),
        "task_index": scalar(&task_index),
    });
    write_table(
        &data_dir.join("file-000.parquet"),
        &[
            ("observation.state", Column::F32List(state)),
            ("action", Column::F32List(action)),
            ("timestamp", Column::F32(timestamp)),
            ("frame_index", Column::I64(frame_index)),
            ("episode_index", Column::I64(episode_index)),
            ("index", Column::I64(index)),
            ("task_index", Column::I64(task_index)),
        ],
        Vec::new(),
    )?;
    let meta = out.join("meta");
    let episodes_dir = meta.join("episodes/chunk-000");
    fs::create_dir_all(&episodes_dir).map_err(io_err(&episodes_dir))?;
    let n_episodes = ep.episode_index.len();
    ep.write(&episodes_dir.join("file-000.parquet"))?;
    // pandas reads `task` back as the index, as LeRobot's `load_tasks` expects.
    let pandas = json!({
        "index_columns": ["task"],
        "column_indexes": [{"name": null, "field_name": null, "pandas_type": "unicode", "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64", "metadata": null},
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": null}
        ],
        "creator": {"library": "libero-agent", "version": env!("CARGO_PKG_VERSION")},
        "pandas_version": "2.2.0"
    });
    write_table(
        &meta.join("tasks.parquet"),
        &[("task_index", Column::I64((0..tasks.len() as i64).collect())), ("task", Column::Str(tasks.clone()))],
        vec![KeyValue::new("pandas".into(), pandas.to_string())],
    )?;
    let info = json!({
        "codebase_version": CODEBASE_VERSION,
        "robot_type": "panda",
        "total_episodes": n_episodes,
        "total_frames": total_frames,
        "total_tasks": tasks.len(),
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 500,
        "fps": DEMO_VIDEO_FPS_HZ as u32,
        "splits": {"train": format!("0:{n_episodes}")},
        "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
        "features": {
            HEAD_KEY: video_feature(),
            WRIST_KEY: video_feature(),
            "observation.state": {"dtype": "float32", "shape": [8], "names": STATE_NAMES},
            "action": {"dtype": "float32", "shape": [7], "names": ACTION_COMPONENTS},
            "timestamp": {"dtype": "float32", "shape": [1], "names": null},
            "frame_index": {"dtype": "int64", "shape": [1], "names": null},
            "episode_index": {"dtype": "int64", "shape": [1], "names": null},
            "index": {"dtype": "int64", "shape": [1], "names": null},
            "task_index": {"dtype": "int64", "shape": [1], "names": null},
        },
    });
    for (name, value) in [("info.json", info), ("stats.json", stats_json)] {
        let p = meta.join(name);
        let text = serde_json::to_string_pretty(&value).map_err(|e| DemoError::Export(e.to_string()))?;
        fs::write(&p, text + "\n").map_err(io_err(&p))?;
    }
    Ok(ExportSummary { out: out.to_owned(), episodes: n_episodes, frames: total_frames, tasks: tasks.len() })
}

#[derive(Default)]
struct EpisodeColumns {
    episode_index: Vec<i64>,
    tasks: Vec<Vec<String>>,
    length: Vec<i64>,
    from_index: Vec<i64>,
    to_index: Vec<i64>,
    video_chunk: Vec<i64>,
    video_file: Vec<i64>,
    to_timestamp_s: Vec<f64>,
}

impl EpisodeColumns {
    fn push(&mut self, e: usize, tasks: Vec<String>, length: usize, from: usize, chunk: i64, file: i64) {
        self.episode_index.push(e as i64);
        self.tasks.push(tasks);
        self.length.push(length as i64);
        self.from_index.push(from as i64);
        self.to_index.push((from + length) as i64);
        self.video_chunk.push(chunk);
        self.video_file.push(file);
        self.to_timestamp_s.push(length as f64 / DEMO_VIDEO_FPS_HZ);
    }

    fn write(self, path: &Path) -> Result<(), DemoError> {
        let n = self.episode_index.len();
        let zeros = vec![0i64; n];
        let mut cols: Vec<(String, Column)> = vec![
            ("episode_index".into(), Column::I64(self.episode_index)),
            ("tasks".into(), Column::StrList(self.tasks)),
            ("length".into(), Column::I64(self.length)),
            ("data/chunk_index".into(), Column::I64(zeros.clone())),
            ("data/file_index".into(), Column::I64(zeros.clone())),
            ("dataset_from_index".into(), Column::I64(self.from_index)),
            ("dataset_to_index".into(), Column::I64(self.to_index)),
        ];
        for key in [HEAD_KEY, WRIST_KEY] {
            cols.push((format!("videos/{key}/chunk_index"), Column::I64(self.video_chunk.clone())));
            cols.push((format!("videos/{key}/file_index"), Column::I64(self.video_file.clone())));
            cols.push((format!("videos/{key}/from_timestamp"), Column::F64(vec![0.0; n])));
            cols.push((format!("videos/{key}/to_timestamp"), Column::F64(self.to_timestamp_s.clone())));
        }
        cols.push(("meta/episodes/chunk_index".into(), Column::I64(zeros.clone())));
        cols.push(("meta/episodes/file_index".into(), Column::I64(zeros)));
        write_table(path, &cols, Vec::new())
    }
}

//! The operator API's episode replies on the wire, pinned by fixtures: the keys, their order (alphabetical, as the
//! untyped replies had them) and their nulls, which the console's JavaScript and every API client read.
use libero_records::episode_view::{EpisodeList, EpisodeState, EpisodeVideo, EpisodeView, VideoState, VideoStatus};
use libero_records::records::Outcome;

fn fixture(name: &str) -> String {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures").join(name);
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// An episode this process runs (live fields present) and an ended one it does not (live fields absent).
fn list() -> EpisodeList {
    let live = EpisodeView {
        accepted_agent_steps: Some(3),
        batch: Some("smoke".into()),
        branch_parent: Some("ep-20261207T140000Z-aaaa".into()),
        branch_step: Some(12),
        completed_stage_count: None,
        created_at: "2026-12-07T14:08:28.383004+00:00".into(),
        finished_at: None,
        harness: Some("codex".into()),
        id: "ep-20261207T140828Z-bbbb".into(),
        init_index: 4,
        latest_observation_id: Some(Some("obs-000003".into())),
        level: 3,
        model: Some("gpt-5".into()),
        outcome: None,
        reason: None,
        required_stage_count: Some(2),
        seed: 7,
        server_url: Some("http://worker-3.lab:8090".into()),
        started_at: Some("2026-12-07T14:08:30.000000+00:00".into()),
        state: Some(EpisodeState::Active),
        success: None,
        task_ref: "T14".into(),
        wall_time_s: None,
    };
    let ended = EpisodeView {
        accepted_agent_steps: Some(40),
        batch: None,
        branch_parent: None,
        branch_step: None,
        completed_stage_count: Some(1),
        created_at: "2026-12-07T13:00:00.000000+00:00".into(),
        finished_at: Some("2026-12-07T13:30:01.500000+00:00".into()),
        harness: None,
        id: "ep-20261207T130000Z-cccc".into(),
        init_index: 0,
        latest_observation_id: None,
        level: 1,
        model: None,
        outcome: Some(Outcome::SimTimeout),
        reason: Some("episode_wall_time_budget_exhausted".into()),
        required_stage_count: Some(2),
        seed: -1,
        server_url: None,
        started_at: Some("2026-12-07T13:00:01.000000+00:00".into()),
        state: None,
        success: Some(false),
        task_ref: "T03".into(),
        wall_time_s: Some(1800.25),
    };
    EpisodeList::new(vec![live, ended])
}

fn videos() -> Vec<EpisodeVideo> {
    let status = |state, percent, frames: Option<(u64, u64)>, error: Option<&str>| VideoStatus {
        error: error.map(str::to_owned),
        frames_done: frames.map(|f| f.0),
        frames_total: frames.map(|f| f.1),
        percent,
        state,
    };
    vec![
        EpisodeVideo { video: false, video_status: None },
        EpisodeVideo { video: false, video_status: Some(status(VideoState::Queued, Some(0), None, None)) },
        EpisodeVideo { video: false, video_status: Some(status(VideoState::Rendering, Some(25), Some((30, 120)), None)) },
        EpisodeVideo { video: true, video_status: Some(status(VideoState::Ready, Some(100), None, None)) },
        EpisodeVideo { video: false, video_status: Some(status(VideoState::Failed, None, None, Some("ffmpeg exited 1"))) },
    ]
}

#[test]
fn the_episode_list_serialises_as_the_fixture_byte_for_byte() {
    let text = serde_json::to_string_pretty(&list()).unwrap();
    assert_eq!(text.trim_end(), fixture("episode_list.json").trim_end());
}

#[test]
fn the_episode_list_fixture_deserialises_to_the_same_views() {
    let read: EpisodeList = serde_json::from_str(&fixture("episode_list.json")).unwrap();
    assert_eq!(read, list());
    let live = &read.episodes[0];
    assert_eq!((live.state, live.latest_observation_id.clone()), (Some(EpisodeState::Active), Some(Some("obs-000003".into()))));
    assert!(!live.has_ended() && read.episodes[1].has_ended());
}

#[test]
fn a_live_episode_without_an_observation_keeps_its_null_and_a_stored_one_has_no_live_keys() {
    let mut view = list().episodes.remove(0);
    view.latest_observation_id = Some(None);
    let value = serde_json::to_value(&view).unwrap();
    assert_eq!(value.get("latest_observation_id"), Some(&serde_json::Value::Null), "{value}");
    assert_eq!(serde_json::from_value::<EpisodeView>(value).unwrap().latest_observation_id, Some(None));
    let stored = serde_json::to_value(&list().episodes[1]).unwrap();
    assert!(stored.get("state").is_none() && stored.get("latest_observation_id").is_none(), "{stored}");
}

#[test]
fn video_replies_serialise_as_the_fixture_and_read_back() {
    let text = serde_json::to_string_pretty(&videos()).unwrap();
    assert_eq!(text.trim_end(), fixture("episode_video.json").trim_end());
    let read: Vec<EpisodeVideo> = serde_json::from_str(&fixture("episode_video.json")).unwrap();
    assert_eq!(read, videos());
}

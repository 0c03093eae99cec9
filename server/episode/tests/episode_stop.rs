//! A shutdown never waits on a stuck episode: `request_stop` + `wait_until` answers by its deadline even when the
//! episode thread is blocked inside the world (a simulation that never returns), and the abort is still recorded
//! once the thread is free. A synthetic world: the rule is the actor's, not the simulation's.
use std::sync::mpsc;
use std::time::{Duration, Instant};

use libero_records::records::{RunDir, read_result};
use libero_episode::{EpisodeConfig, EpisodeError, Frame, Level, MicroAction, Verdict, World, spawn_episode};

fn config(dir: &std::path::Path, name: &str) -> EpisodeConfig {
    EpisodeConfig {
        episode_id: name.into(),
        instruction: "stop test".into(),
        level: Level::L1,
        max_agent_steps: 10,
        max_wall_time_s: 60.0,
        workspace: dir.join(name).join("ws"),
        run_dir: dir.join(name).join("run"),
    }
}

#[test]
fn an_episode_thread_blocked_in_the_world_does_not_hold_the_stop() {
    /// A world that blocks in `start`, the first thing a started episode does.
    struct StuckAtStart(mpsc::Receiver<()>);
    impl World for StuckAtStart {
        fn start(&mut self) -> Result<(), EpisodeError> {
            let _ = self.0.recv();
            Ok(())
        }
        fn step(&mut self, _: &MicroAction) -> Result<(), EpisodeError> {
            Ok(())
        }
        fn frame(&mut self, i: u64) -> Result<Frame, EpisodeError> {
            Err(EpisodeError::Thread(format!("no frames ({i})")))
        }
        fn verdict(&mut self) -> Result<Verdict, EpisodeError> {
            Ok(Verdict { success: false, private_evaluation: serde_json::json!({}), stage_events: vec![] })
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let (release_tx, release_rx) = mpsc::channel::<()>();
    let handle = spawn_episode(config(dir.path(), "blocked"), move || Ok(StuckAtStart(release_rx))).unwrap();
    let h = handle.clone();
    let caller = std::thread::spawn(move || h.call("start_episode", None));
    std::thread::sleep(Duration::from_millis(200));
    let started = Instant::now();
    let answered = handle.request_stop("test shutdown").wait_until(Instant::now() + Duration::from_millis(300));
    assert!(!answered, "the stuck thread cannot answer");
    assert!(started.elapsed() < Duration::from_secs(3), "the wait ended at its deadline: {:?}", started.elapsed());
    // Released, the thread finishes the call, then takes the stop and records the abort.
    drop(release_tx);
    let _ = caller.join().unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    let run = RunDir::new(dir.path().join("blocked/run"));
    while read_result(&run).is_none() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(read_result(&run).is_some(), "the abort is recorded once the thread is free");
}

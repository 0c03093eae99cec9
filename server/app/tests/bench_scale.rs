//! Issue 34, item 3: `libero-agent bench scale` against a real `serve`, as small as it goes (two T14 episodes on
//! one scene, two short timed calls): the JSON names every figure, and the figures agree with one another as the
//! bench defines them (an episode's open time is its prepare plus its start, a summary of one episode is that
//! episode, the sizing is the increments' sum, a CPU time read from `/proc` is whole clock ticks). No timing is
//! compared with a threshold: the machine is shared.
#![cfg(feature = "episode-serve")]

use std::process::Command;

use serde_json::Value;

fn num(v: &Value, pointer: &str) -> f64 {
    v.pointer(pointer).and_then(Value::as_f64).unwrap_or_else(|| panic!("{pointer} missing or not a number in {v}"))
}

#[test]
fn bench_scale_reports_memory_threads_open_times_and_latency() {
    let out = Command::new(env!("CARGO_BIN_EXE_libero-agent"))
        .args(["bench", "scale", "--episodes", "2", "--scenes", "1", "--calls", "2", "--actions", "5", "--settle-ms", "300", "--json"])
        .output()
        .expect("run libero-agent bench scale");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "bench scale failed: {stderr}");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let v: Value = serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("not JSON ({e}): {stdout}"));

    assert_eq!(v["benchmark"], "scale");
    assert_eq!(v["episodes"], 2);
    assert_eq!(v["scenes"], serde_json::json!(["T14"]));
    assert_eq!(v["video"], false);
    assert!(v["renderer_adapter"].as_str().is_some_and(|a| !a.is_empty()), "{v}");
    assert!(num(&v, "/cpu_cores") >= 1.0 && num(&v, "/mem_total_gb") > 0.0);

    // Resident memory and threads of the serve process: idle, 1 open, 2 open, after finishing.
    for at in ["idle", "one_open", "n_open", "after_finish"] {
        assert!(num(&v, &format!("/{at}/rss_mb")) > 1.0, "{at}: {v}");
        assert!(num(&v, &format!("/{at}/threads")) >= 1.0, "{at}: {v}");
    }
    assert!(num(&v, "/one_open/rss_mb") > num(&v, "/idle/rss_mb"), "an open episode holds memory: {v}");
    assert!(num(&v, "/n_open/rss_mb") > num(&v, "/idle/rss_mb"), "{v}");
    assert_eq!(num(&v, "/n_open/episodes"), 2.0);
    assert!(num(&v, "/per_open_episode_mb") > 0.0);
    let per_open = (num(&v, "/n_open/rss_mb") - num(&v, "/idle/rss_mb")) / 2.0;
    assert!(close(num(&v, "/per_open_episode_mb"), per_open), "per_open_episode_mb is (n_open - idle) / episodes: {v}");

    // One first episode of the scene, one additional: both increments, both open times.
    for kind in ["first_of_scene", "additional"] {
        assert_eq!(num(&v, &format!("/increments/{kind}/rss_mb/count")), 1.0, "{kind}: {v}");
        num(&v, &format!("/increments/{kind}/rss_mb/mean"));
        num(&v, &format!("/increments/{kind}/threads/mean"));
    }
    assert!(num(&v, "/increments/first_of_scene/rss_mb/mean") > 0.0, "{v}");
    assert!(num(&v, "/increments/first_episode_of_the_server/rss_mb") > 0.0, "{v}");
    assert!(v["increments"]["first_of_scene_after_the_first"]["rss_mb"].is_null(), "one scene has no later first: {v}");
    // How long the episodes' threads took to exit is a timing: only its presence is checked.
    num(&v, "/after_finish/episode_threads_gone_after_s");
    for kind in ["cold", "warm", "cold_prepare", "warm_prepare"] {
        assert!(num(&v, &format!("/open_ms/{kind}/p50")) > 0.0, "{kind}: {v}");
    }
    let episodes = v["per_episode"].as_array().expect("per_episode");
    assert_eq!(episodes.len(), 2);
    assert_eq!((episodes[0]["first_of_scene"].as_bool(), episodes[1]["first_of_scene"].as_bool()), (Some(true), Some(false)));
    assert!(episodes.iter().all(|e| e["task"] == "T14" && e["open_ms"].as_f64().is_some_and(|t| t > 0.0)), "{v}");
    let ids: std::collections::BTreeSet<&str> = episodes.iter().filter_map(|e| e["episode_id"].as_str()).collect();
    assert_eq!(ids.len(), 2, "two distinct episodes: {v}");
    for (i, e) in episodes.iter().enumerate() {
        let (prepare, start, open) = (num(e, "/prepare_ms"), num(e, "/start_episode_ms"), num(e, "/open_ms"));
        assert!(close(open, prepare + start) && prepare <= open && start <= open, "episode {i}: open is prepare + start: {e}");
        assert_eq!(e["index"], i, "{e}");
    }
    // Each kind holds one episode here, so its summaries are that episode's own figures.
    for (kind, e) in [("first_of_scene", &episodes[0]), ("additional", &episodes[1])] {
        assert!(close(num(&v, &format!("/increments/{kind}/rss_mb/mean")), num(e, "/rss_increment_mb")), "{kind}: {v}");
        assert!(close(num(&v, &format!("/increments/{kind}/threads/mean")), num(e, "/thread_increment")), "{kind}: {v}");
    }
    assert!(close(num(&v, "/increments/first_episode_of_the_server/rss_mb"), num(&episodes[0], "/rss_increment_mb")), "{v}");
    for (kind, e, key) in [("cold", &episodes[0], "open_ms"), ("warm", &episodes[1], "open_ms"), ("cold_prepare", &episodes[0], "prepare_ms"), ("warm_prepare", &episodes[1], "prepare_ms")] {
        for stat in ["p50", "mean", "min", "max"] {
            assert!(close(num(&v, &format!("/open_ms/{kind}/{stat}")), num(e, &format!("/{key}"))), "open_ms/{kind}/{stat}: {v}");
        }
        assert_eq!(num(&v, &format!("/open_ms/{kind}/count")), 1.0, "{kind}: {v}");
    }

    // osc_sequence with 1 and with 2 open episodes, one driven.
    for at in ["one_open", "n_open"] {
        let (p50, p95) = (num(&v, &format!("/osc_sequence/{at}/p50_ms")), num(&v, &format!("/osc_sequence/{at}/p95_ms")));
        assert!(p50 > 0.0 && p95 >= p50, "{at}: {v}");
        assert_eq!(num(&v, &format!("/osc_sequence/{at}/calls")), 2.0);
        // The server's CPU time over the calls is the difference of two /proc readings, each whole clock ticks.
        let ticks = num(&v, &format!("/osc_sequence/{at}/server_cpu_ms_per_call")) * 2.0 / 1e3 * clock_ticks_per_s();
        assert!(ticks > -1e-6 && (ticks - ticks.round()).abs() < 1e-6, "{at}: {ticks} clock ticks: {v}");
    }
    assert_eq!(num(&v, "/osc_sequence/one_open/open_episodes"), 1.0);
    assert_eq!(num(&v, "/osc_sequence/n_open/open_episodes"), 2.0);
    assert_eq!(num(&v, "/osc_sequence/actions_per_call"), 5.0);
    let idle_cpu = (num(&v, "/server_cpu_idle_percent/n_open") - num(&v, "/server_cpu_idle_percent/no_episode")) / 2.0;
    assert!(close(num(&v, "/server_cpu_idle_percent/per_open_episode"), idle_cpu), "per open episode is the difference / episodes: {v}");

    // The main-table projection from those increments.
    assert_eq!(num(&v, "/sizing/main_table_rollouts"), 90.0);
    assert!(num(&v, "/sizing/main_table_all_open_rss_gb") > 0.0 && num(&v, "/sizing/episodes_per_gb") > 0.0, "{v}");
    // One scene: no later first of a scene was measured, so the other 29 scenes take the server's first episode's
    // increment; the 60 additional episodes take the measured additional one.
    assert_eq!((v["sizing"]["later_first_of_scene_measured"].as_bool(), v["sizing"]["additional_measured"].as_bool()), (Some(false), Some(true)));
    let first = num(&v, "/increments/first_episode_of_the_server/rss_mb");
    let batch_gb = (num(&v, "/idle/rss_mb") + 30.0 * first + 60.0 * num(&v, "/increments/additional/rss_mb/mean")) / 1024.0;
    assert!(close(num(&v, "/sizing/main_table_all_open_rss_gb"), batch_gb), "the batch is idle + 30 first + 60 additional: {v}");
    assert!(close(num(&v, "/sizing/episodes_per_gb"), 90.0 / batch_gb), "{v}");
}

/// Equal up to floating-point rounding.
fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1.0)
}

/// The kernel's clock ticks per second, the unit of the CPU times in `/proc/<pid>/stat`.
fn clock_ticks_per_s() -> f64 {
    // SAFETY: sysconf only reads a system constant.
    unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as f64
}

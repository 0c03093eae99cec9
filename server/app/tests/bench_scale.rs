//! Issue 34, item 3: `libero-agent bench scale` against a real `serve`, as small as it goes (two T14 episodes on
//! one scene, two short timed calls): the JSON names every figure, each with a sane value. No timing is asserted.
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

    // One first episode of the scene, one additional: both increments, both open times.
    for kind in ["first_of_scene", "additional"] {
        assert_eq!(num(&v, &format!("/increments/{kind}/rss_mb/count")), 1.0, "{kind}: {v}");
        num(&v, &format!("/increments/{kind}/rss_mb/mean"));
        num(&v, &format!("/increments/{kind}/threads/mean"));
    }
    assert!(num(&v, "/increments/first_of_scene/rss_mb/mean") > 0.0, "{v}");
    assert!(num(&v, "/increments/first_episode_of_the_server/rss_mb") > 0.0, "{v}");
    assert!(v["increments"]["first_of_scene_after_the_first"]["rss_mb"].is_null(), "one scene has no later first: {v}");
    assert!(num(&v, "/after_finish/episode_threads_gone_after_s") >= 0.0);
    for kind in ["cold", "warm", "cold_prepare", "warm_prepare"] {
        assert!(num(&v, &format!("/open_ms/{kind}/p50")) > 0.0, "{kind}: {v}");
    }
    let episodes = v["per_episode"].as_array().expect("per_episode");
    assert_eq!(episodes.len(), 2);
    assert_eq!((episodes[0]["first_of_scene"].as_bool(), episodes[1]["first_of_scene"].as_bool()), (Some(true), Some(false)));
    assert!(episodes.iter().all(|e| e["task"] == "T14" && e["open_ms"].as_f64().is_some_and(|t| t > 0.0)), "{v}");

    // osc_sequence with 1 and with 2 open episodes, one driven.
    for at in ["one_open", "n_open"] {
        let (p50, p95) = (num(&v, &format!("/osc_sequence/{at}/p50_ms")), num(&v, &format!("/osc_sequence/{at}/p95_ms")));
        assert!(p50 > 0.0 && p95 >= p50, "{at}: {v}");
        assert_eq!(num(&v, &format!("/osc_sequence/{at}/calls")), 2.0);
        assert!(num(&v, &format!("/osc_sequence/{at}/server_cpu_ms_per_call")) >= 0.0);
    }
    assert_eq!(num(&v, "/osc_sequence/n_open/open_episodes"), 2.0);
    assert!(num(&v, "/server_cpu_idle_percent/n_open") >= 0.0);

    // The main-table projection from those increments.
    assert_eq!(num(&v, "/sizing/main_table_rollouts"), 90.0);
    assert!(num(&v, "/sizing/main_table_all_open_rss_gb") > 0.0 && num(&v, "/sizing/episodes_per_gb") > 0.0, "{v}");
}

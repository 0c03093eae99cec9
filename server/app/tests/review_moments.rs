//! Issue 49, item 1: an episode without a private video is reviewed from its recorded state. A real `serve`, T28's
//! expert run with `--no-video` through it, the moment route (`/api/episodes/{id}/moment?step=N`) and its errors,
//! and chromium on the review page: moments per control step that match what the agent observed, plots, stepping,
//! play and "Continue from here" at the step shown.
mod common;

/// T28's expert on `server` without a video: (episode id, actions executed).
fn play_t28_without_video(server: &common::Server) -> (String, u64) {
    let v = common::expert_on_server(&server.url, "T28");
    (v["episode_id"].as_str().expect("episode id").to_owned(), v["actions"].as_u64().expect("actions"))
}

fn header<'a>(headers: &'a str, name: &str) -> Option<&'a str> {
    headers.lines().find_map(|l| l.split_once(':').filter(|(k, _)| k.trim().eq_ignore_ascii_case(name)).map(|(_, v)| v.trim()))
}

#[test]
fn an_episode_without_video_is_reviewed_from_moments_rendered_from_its_recorded_state() {
    let data = tempfile::tempdir().unwrap();
    let server = common::Server::start(data.path());
    let (id, actions) = play_t28_without_video(&server);
    assert!(!data.path().join("runs").join(&id).join("continuous_video.mp4").exists(), "the episode has no video");
    let auth = format!("Bearer {}", server.token);
    let get = |path: &str, auth: Option<&str>| {
        let headers: Vec<(&str, &str)> = auth.map(|a| vec![("Authorization", a)]).unwrap_or_default();
        common::http("GET", &format!("{}{path}", server.url), &headers, b"")
    };

    // Every control step from the settled start (0) to the last action has its moment: a JPEG naming its step.
    for step in [0, actions / 2, actions] {
        let (status, headers, body) = get(&format!("/api/episodes/{id}/moment?step={step}"), Some(&auth));
        assert_eq!(status, 200, "step {step}: {}", String::from_utf8_lossy(&body));
        assert_eq!(header(&headers, "content-type"), Some("image/jpeg"));
        assert_eq!(header(&headers, "x-control-step"), Some(step.to_string().as_str()));
        assert_eq!(header(&headers, "x-control-steps"), Some(actions.to_string().as_str()));
        assert!(body.starts_with(&[0xFF, 0xD8]) && body.len() > 5000, "a JPEG of a scene ({} bytes)", body.len());
    }
    // Bad input gets a clear error and renders nothing.
    for (query, status, says) in [
        ("step=abc".to_owned(), 400, "step must be a control step number".to_owned()),
        (String::new(), 400, "step must be a control step number".to_owned()),
        ("step=-1".to_owned(), 400, "step must be a control step number".to_owned()),
        (format!("step={}", actions + 1), 400, format!("control step {} is past the episode's last ({actions} control steps", actions + 1)),
    ] {
        let (got, _, body) = get(&format!("/api/episodes/{id}/moment?{query}"), Some(&auth));
        let body = String::from_utf8_lossy(&body);
        assert_eq!(got, status, "{query}: {body}");
        assert!(body.contains(&says), "{query}: {body}");
    }
    let (got, _, _) = get("/api/episodes/ep-20990101T000000Z-deadbeef/moment?step=0", Some(&auth));
    assert_eq!(got, 404, "an unknown episode");
    // Operator-only: without the operator's credential, or with an episode's token, nothing is rendered.
    let prepared = common::prepare_t14(&server.url, &data.path().join("agent-ws"));
    let agent = prepared["mcp_headers"]["Authorization"].as_str().expect("the episode's token").to_owned();
    for credential in [None, Some(agent.as_str())] {
        let (got, _, body) = get(&format!("/api/episodes/{id}/moment?step=0"), credential);
        assert!(got == 401 || got == 303, "{credential:?}: {got}");
        assert!(!body.starts_with(&[0xFF, 0xD8]));
    }

    // Chromium: the review opened at step 120 shows moments, plots, steps, plays and continues from the step shown.
    let artifacts = std::env::temp_dir().join("libero-agent-review-moments");
    std::fs::create_dir_all(&artifacts).unwrap();
    let report = common::browser_script("review_moments_check.cjs", &[&server.url, &id, "120", artifacts.to_str().expect("utf-8")], &server.token);
    assert_eq!(report["ok"], true, "{report}");
    let branch_step = report["branch_step"].as_u64().expect("the branch's step");
    assert!(branch_step > 120, "play moved past the opened moment before the branch: {report}");
    let (_, rows) = common::http_get_json(&format!("{}/api/episodes", server.url));
    let branch = rows["episodes"].as_array().expect("episodes").iter().find(|r| r["branch_parent"] == id.as_str()).cloned();
    let branch = branch.unwrap_or_else(|| panic!("a branch of {id}: {rows}"));
    assert_eq!(branch["branch_step"].as_u64(), Some(branch_step), "{branch}");
    assert_eq!((branch["harness"].as_str(), branch["model"].as_str(), branch["batch"].as_str()), (Some("expert"), Some("solve"), None), "{branch}");
}

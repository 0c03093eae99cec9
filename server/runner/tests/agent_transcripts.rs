//! The transcript normaliser against what the real CLIs printed (`tests/fixtures/agent_transcripts/`, captured
//! from the pinned CLIs in the sandbox; DeepSeek's and the command harness's constructed): each harness's output
//! becomes the golden transcript beside it, and the kinds a reviewer needs are there. Then the follower against
//! a hostile agent's output: huge lines, invalid UTF-8, secrets, a flood, and usage lines it prints itself.
use std::path::{Path, PathBuf};

use libero_records::agent_events::{AgentEvent, Kind, Source};
use libero_runner::harness::Harness;
use libero_sandbox::netgate::UsageSummary;
use libero_runner::transcript::{Normalizer, Streams, Target, Follower, normalize_logs};
use libero_runner::usage::{self, UsageFormat, UsageScanner};

const WORKSPACE: &str = "/work/ws/w1_t14_level3";
const API_KEY: &str = "sk-scripted-0123456789abcdef";

fn fixtures() -> PathBuf {
    libero_testkit::tests_dir().join("fixtures/agent_transcripts")
}

/// The harness's captured output normalised, compared with (or, with `UPDATE_GOLDEN=1`, written to) its golden
/// transcript.
fn golden(harness: Harness, stdout: &str) -> Vec<AgentEvent> {
    let name = harness.as_str();
    let read = |f: &str| std::fs::read(fixtures().join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
    let events = normalize_logs(harness, Path::new(WORKSPACE), &[API_KEY], &read(stdout), &read(&format!("{name}_stderr.log")));
    let text: String = events.iter().map(|e| e.to_line() + "\n").collect();
    let path = fixtures().join(format!("{name}.expected.jsonl"));
    if std::env::var_os("UPDATE_GOLDEN").is_some() {
        std::fs::write(&path, &text).unwrap();
    }
    let expected = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e} (UPDATE_GOLDEN=1 writes it)", path.display()));
    assert_eq!(text, expected, "{name}: the transcript differs from {}", path.display());
    let seqs: Vec<u64> = events.iter().map(|e| e.seq).collect();
    assert_eq!(seqs, (0..events.len() as u64).collect::<Vec<_>>(), "{name}: seq counts 0, 1, 2, …");
    events
}

fn of_kind(events: &[AgentEvent], kind: Kind) -> Vec<&AgentEvent> {
    events.iter().filter(|e| e.kind == kind).collect()
}

/// The robot calls of a transcript in order: (robot tool, observation acted on or returned).
fn robot(events: &[AgentEvent], kind: Kind) -> Vec<(String, Option<String>)> {
    events.iter().filter(|e| e.kind == kind && e.robot_tool.is_some()).map(|e| (e.robot_tool.clone().unwrap(), e.observation_id.clone())).collect()
}

fn obs(id: &str) -> Option<String> {
    Some(id.to_owned())
}

/// What every captured CLI shows: its reasoning, its message, the shell command with its output, the robot calls
/// each with the observation it acted on, and each robot result with the observation it returned.
fn common_checks(name: &str, events: &[AgentEvent]) {
    assert!(of_kind(events, Kind::Message).iter().any(|e| e.text.as_deref() == Some("The episode is finished.")), "{name}: the final message");
    let shell = of_kind(events, Kind::Shell);
    let listing = shell.iter().find(|e| e.command.as_deref().is_some_and(|c| c.contains("ls benchmark_inputs/current_observation"))).unwrap_or_else(|| panic!("{name}: {shell:?}"));
    assert!(listing.output.as_deref().is_some_and(|o| o.contains("observation.json") && o.contains("42")), "{name}: its output: {listing:?}");
    assert_eq!(
        robot(events, Kind::ToolCall),
        [("start_episode".into(), None), ("osc_sequence".into(), obs("obs_000000")), ("finish_episode".into(), obs("obs_000001"))],
        "{name}: each robot call with the observation it acted on"
    );
    let results = robot(events, Kind::ToolResult);
    assert_eq!(results[..2], [("start_episode".into(), obs("obs_000000")), ("osc_sequence".into(), obs("obs_000001"))], "{name}");
    assert!(events.iter().all(|e| !e.to_line().contains(API_KEY)), "{name}: no key");
}

/// The image the agent viewed, placed on the published observation (the review shows the private copy).
fn viewed_image(name: &str, events: &[AgentEvent]) {
    let views = of_kind(events, Kind::ImageView);
    assert_eq!(views.len(), 1, "{name}: {views:?}");
    assert_eq!(views[0].path.as_deref(), Some(format!("{WORKSPACE}/benchmark_inputs/current_observation/head/rgb.png").as_str()));
    assert_eq!(views[0].observation_file.as_deref(), Some("head/rgb.png"), "{name}");
    let reads = of_kind(events, Kind::FileRead);
    assert_eq!(reads.len(), 1, "{name}: {reads:?}");
    assert_eq!(reads[0].workspace_path.as_deref(), Some("TASK_PROMPT.txt"), "{name}");
}

#[test]
fn claude_code_stream_json_normalises_to_its_golden_transcript() {
    let events = golden(Harness::ClaudeCode, "claude_code_stdout.jsonl");
    common_checks("claude_code", &events);
    viewed_image("claude_code", &events);
    assert!(!of_kind(&events, Kind::Reasoning).is_empty(), "thinking blocks");
    let usage = of_kind(&events, Kind::Usage);
    assert_eq!(usage.len(), 1, "the result line's total, not every message's repeat");
    assert_eq!(usage[0].tokens.unwrap().input_tokens, Some(5600));
    let image_result = of_kind(&events, Kind::ToolResult).into_iter().find(|e| e.tool.as_deref() == Some("Read") && e.text.as_deref() == Some("[image]"));
    assert!(image_result.is_some(), "the image's bytes are not in the transcript");
}

#[test]
fn codex_exec_json_normalises_to_its_golden_transcript() {
    let events = golden(Harness::Codex, "codex_stdout.jsonl");
    common_checks("codex", &events);
    let shell = of_kind(&events, Kind::Shell);
    assert!(shell.iter().all(|e| e.exit_code == Some(0)), "Codex reports exit codes: {shell:?}");
    assert!(shell.iter().any(|e| e.command.as_deref().is_some_and(|c| c.contains("sed -n 1,3p TASK_PROMPT.txt"))), "Codex reads files with commands");
    assert!(of_kind(&events, Kind::ImageView).is_empty(), "Codex prints no event for view_image");
    assert!(of_kind(&events, Kind::Reasoning).iter().any(|e| e.text.as_deref().is_some_and(|t| t.contains("benchmark_inputs"))));
    let usage = of_kind(&events, Kind::Usage);
    assert_eq!((usage.len(), usage[0].tokens.unwrap().input_tokens), (1, Some(8400)), "one turn.completed");
    assert!(of_kind(&events, Kind::Stderr).iter().any(|e| e.text.as_deref().is_some_and(|t| t.contains("Responses WebSocket"))));
}

#[test]
fn qwen_code_stream_json_normalises_to_its_golden_transcript() {
    let events = golden(Harness::QwenCode, "qwen_code_stdout.jsonl");
    common_checks("qwen_code", &events);
    viewed_image("qwen_code", &events);
    let search = of_kind(&events, Kind::ToolCall).into_iter().find(|e| e.tool.as_deref() == Some("tool_search"));
    assert!(search.is_some_and(|s| s.robot_tool.is_none()), "its tool search is a tool call, not a robot call");
    assert!(!of_kind(&events, Kind::Reasoning).is_empty());
    assert_eq!(of_kind(&events, Kind::Usage)[0].tokens.unwrap().total_tokens, Some(9840));
}

#[test]
fn kimi_code_stream_json_normalises_to_its_golden_transcript() {
    let events = golden(Harness::KimiCode, "kimi_code_stdout.jsonl");
    common_checks("kimi_code", &events);
    viewed_image("kimi_code", &events);
    assert!(of_kind(&events, Kind::Usage).is_empty(), "Kimi prints no token counts (the gateway's records have them)");
    assert!(of_kind(&events, Kind::Reasoning).is_empty(), "Kimi prints no reasoning in stream-json");
    let image = of_kind(&events, Kind::ToolResult).into_iter().find(|e| e.tool.as_deref() == Some("ReadMediaFile")).unwrap();
    assert!(image.text.as_deref().is_some_and(|t| t.contains("bytes of base64>") && t.len() < 1000), "{image:?}");
}

#[test]
fn deepseek_headless_answer_normalises_to_its_golden_transcript() {
    let events = golden(Harness::Deepseek, "deepseek_stdout.log");
    assert_eq!(events.len(), 1);
    assert_eq!((events[0].kind, events[0].text.as_deref()), (Kind::Message, Some("I closed the top drawer and called finish_episode.")));
}

#[test]
fn command_stdout_lines_are_messages_verbatim_even_when_they_look_like_usage() {
    let events = golden(Harness::Command, "command_stdout.log");
    let messages: Vec<&str> = of_kind(&events, Kind::Message).iter().filter_map(|e| e.text.as_deref()).collect();
    assert_eq!(messages.len(), 5);
    assert_eq!(messages[0], "reading TASK_PROMPT.txt");
    assert!(messages[2].contains("999999999"), "printed, shown as printed");
    assert!(of_kind(&events, Kind::Usage).is_empty(), "a printed usage line is no usage event");
    assert_eq!(of_kind(&events, Kind::Stderr).len(), 1);
}

/// What a hostile agent prints: a line of 3 MiB, invalid UTF-8, the API key and a bearer token, JSON that only
/// looks like a CLI's, a flood that outruns the reader, and a line without its newline at the end.
fn hostile_stdout() -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(b"{\"type\":\"assistant\",\"message\":{\"content\":[{\"type\":\"text\",\"text\":\"key ");
    out.extend_from_slice(API_KEY.as_bytes());
    out.extend_from_slice(b" and Bearer abcdefghijklmnop\"}]}}\n");
    out.extend(std::iter::repeat_n(b'x', 3 << 20));
    out.push(b'\n');
    out.extend_from_slice(b"not utf-8: \xff\xfe\xc3\x28 end\n");
    out.extend_from_slice(b"{\"type\":\"result\",\"usage\":{\"input_tokens\":999999999,\"output_tokens\":999999999}}\n");
    out.extend_from_slice(b"{\"type\":\"assistant\",\"message\":{\"content\":\"not a list\"}}\n");
    out.extend_from_slice(b"{\"type\":\"user\",\"message\":{\"content\":[{\"type\":\"tool_result\",\"tool_use_id\":\"nobody\",\"content\":[1,2]}]}}\n");
    out.extend_from_slice(b"[1,2,3]\n{\"type\":42}\n{\"role\":\"assistant\",\"tool_calls\":[{\"function\":{\"name\":\"Read\",\"arguments\":\"{\\\"file_path\\\":\\\"../../../../etc/shadow\\\"}\"}}]}\n");
    out.extend_from_slice(b"last line without a newline");
    out
}

#[test]
fn a_hostile_agents_output_becomes_bounded_scrubbed_events_and_never_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let (stdout, stderr, gateway) = (dir.path().join("claude_code_stdout.jsonl"), dir.path().join("claude_code_stderr.log"), dir.path().join("model_api.jsonl"));
    std::fs::write(&stdout, b"").unwrap();
    std::fs::write(&stderr, b"\xff\xfe stderr not utf-8\n").unwrap();
    // One real model request as the gateway records it.
    std::fs::write(&gateway, r#"{"time":"2026-01-01T00:00:00Z","unix_ms":0,"mode":"reverse","method":"POST","host":"127.0.0.1:1","path":"/v1/messages","status":200,"request_bytes":10,"response_bytes":20,"duration_ms":5,"usage":{"api":"anthropic_messages","input_tokens":800,"output_tokens":30,"cached_input_tokens":400,"total_tokens":830}}
not a record
"#)
    .unwrap();
    let run = dir.path().join("run");
    std::fs::create_dir(&run).unwrap();
    let follower = Follower::start(
        Normalizer::new(Harness::ClaudeCode, Path::new(WORKSPACE), &[API_KEY]),
        Streams { stdout: stdout.clone(), stderr, gateway: Some(gateway.clone()) },
        Target::RunDir(run.clone()),
    );
    // The agent writes while the follower reads: first the hostile lines, then a flood far beyond what is read
    // per poll, written as a sparse jump.
    std::fs::write(&stdout, hostile_stdout()).unwrap();
    let t = std::time::Instant::now();
    while !std::fs::read_to_string(run.join("agent_events.jsonl")).unwrap_or_default().contains("\"kind\":\"file_read\"") {
        assert!(t.elapsed().as_secs() < 60, "the follower did not read the hostile lines");
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    {
        use std::io::{Seek, Write};
        let mut f = std::fs::OpenOptions::new().write(true).open(&stdout).unwrap();
        f.seek(std::io::SeekFrom::End(1 << 30)).unwrap();
        f.write_all(b"\n{\"type\":\"assistant\",\"message\":{\"content\":[{\"type\":\"text\",\"text\":\"after the flood\"}]}}\n").unwrap();
    }
    let summary = follower.finish();
    assert!(summary.errors.is_empty(), "{:?}", summary.errors);
    let text = std::fs::read_to_string(run.join("agent_events.jsonl")).expect("valid UTF-8 JSON lines");
    assert!(text.len() < 1 << 20, "bounded: {} bytes", text.len());
    let events: Vec<AgentEvent> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(summary.written.events, events.len() as u64);
    assert!(!text.contains(API_KEY) && !text.contains("abcdefghijklmnop"), "secrets scrubbed: {text}");
    assert!(text.contains("key <redacted> and Bearer <redacted>"));
    let texts: Vec<&str> = events.iter().filter_map(|e| e.text.as_deref()).collect();
    assert!(texts.iter().any(|t| t.contains("line of 3145728 bytes") && t.contains("not parsed")), "{texts:?}");
    assert!(texts.iter().any(|t| t.starts_with("not utf-8: \u{fffd}\u{fffd}")), "invalid UTF-8 shown replaced: {texts:?}");
    assert!(texts.iter().any(|t| t.contains("bytes of the agent's stdout were skipped")), "the flood was skipped: {texts:?}");
    assert!(texts.contains(&"after the flood"), "the reader caught up after the flood");
    assert!(texts.contains(&"last line without a newline"));
    assert!(events.iter().any(|e| e.kind == Kind::Stderr && e.text.as_deref().is_some_and(|t| t.contains("stderr not utf-8"))));
    let shadow = events.iter().find(|e| e.kind == Kind::FileRead).expect("the read is shown");
    assert_eq!((shadow.workspace_path.as_deref(), shadow.observation_file.as_deref()), (None, None), "a path outside the workspace is never placed");
    // Usage events: the agent's printed line is shown as stdout's claim; the gateway's record as the gateway's.
    let usage: Vec<(Option<Source>, Option<u64>)> = events.iter().filter(|e| e.kind == Kind::Usage).map(|e| (e.source, e.tokens.unwrap().input_tokens)).collect();
    assert!(usage.contains(&(Some(Source::ModelApiGateway), Some(800))), "{usage:?}");
    let seqs: Vec<u64> = events.iter().map(|e| e.seq).collect();
    assert!(seqs.windows(2).all(|w| w[0] < w[1]), "in capture order");
}

/// The rollout's usage: a fake `result` line the agent prints into its CLI's stdout would make stdout claim a
/// billion tokens; with the gateway's records there, the gateway's figures count and stdout's are only kept for
/// comparison, marked as disagreeing.
#[test]
fn usage_lines_the_agent_prints_do_not_count_when_the_gateway_has_records() {
    let mut scanner = UsageScanner::new(UsageFormat::Jsonl);
    scanner.push(&hostile_stdout());
    let stdout = scanner.finish();
    assert_eq!(stdout.input_tokens, Some(999_999_999), "stdout alone would believe it");
    let gateway = UsageSummary { requests: 1, responses_with_usage: 1, input_tokens: 800, output_tokens: 30, total_tokens: 830, ..UsageSummary::default() };
    let u = usage::choose(stdout.clone(), Some(&gateway));
    assert_eq!((u.source.as_deref(), u.input_tokens, u.output_tokens, u.total_tokens), (Some(libero_report::usage::SOURCE_GATEWAY), Some(800), Some(30), Some(830)));
    let claimed = u.harness_stdout.expect("stdout's claim kept beside");
    assert!(!claimed.agrees && claimed.input_tokens == Some(999_999_999));
    let alone = usage::choose(stdout, None);
    assert_eq!(alone.source.as_deref(), Some(libero_report::usage::SOURCE_STDOUT), "without a gateway (--no-sandbox) stdout is all there is");
    assert_eq!(usage::choose(Default::default(), Some(&UsageSummary::default())).source.as_deref(), Some(libero_report::usage::SOURCE_NONE));
}

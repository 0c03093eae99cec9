//! `tests/clis/scripted_model.py` on a free loopback port: the model API of the tests, with no model.
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use serde_json::Value;

use super::{first_json_line, python};

/// The API key the scripted model accepts (it reads it from its environment, never a command line).
pub const API_KEY: &str = "sk-scripted-0123456789abcdef";

/// The scripted model, killed on drop.
pub struct ScriptedModel {
    child: Child,
    pub port: u16,
    log: PathBuf,
}

impl ScriptedModel {
    pub fn start(dir: &Path) -> Self {
        Self::start_script(dir, "robot")
    }

    /// With one of its scripts: `robot` (the episode's tools only) or `perception` (start, the CLI's shell running
    /// `tests/clis/perception_program.py`, an `osc_sequence` read from its output, finish).
    pub fn start_script(dir: &Path, script: &str) -> Self {
        let log = dir.join("model_requests.jsonl");
        let program = libero_testkit::tests_dir().join("clis/scripted_model.py");
        let mut child = Command::new(python())
            .arg(program)
            .arg("--log")
            .arg(&log)
            .args(["--script", script])
            .env("SCRIPTED_MODEL_API_KEY", API_KEY)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start the scripted model");
        let port = first_json_line(&mut child)["port"].as_u64().expect("port") as u16;
        Self { child, port, log }
    }

    /// A credentials file for `run --credentials-file` naming this model.
    pub fn credentials(&self, dir: &Path) -> PathBuf {
        let creds = dir.join("credentials");
        std::fs::write(&creds, format!("APIKEY={API_KEY}\nAPIURL=http://127.0.0.1:{}\n", self.port)).unwrap();
        creds
    }

    /// The requests it answered (not the refused ones).
    pub fn answered(&self) -> Vec<Value> {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        text.lines()
            .filter(|l| !l.trim().is_empty())
            .map(|l| serde_json::from_str::<Value>(l).unwrap())
            .filter(|r| r["method"] == "POST" && r.get("refused").is_none())
            .collect()
    }
}

impl Drop for ScriptedModel {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

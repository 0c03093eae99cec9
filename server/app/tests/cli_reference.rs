//! `docs/cli.md` is the binary's own `--help`, so it cannot drift: `libero-agent --help` and every subcommand's
//! `--help`, recursively (subcommands of subcommands), in the order the binary lists them. This test regenerates the
//! reference from the binary of this build and fails with a diff when the file differs. To regenerate it:
//!
//! ```sh
//! UPDATE_CLI_REFERENCE=1 cargo test -p libero-agent --test cli_reference
//! ```
//!
//! The help is taken with a cleared environment (only `HOME=/home/user` and `PATH`), so that values clap shows from
//! the environment (`[env: …=value]`) or the home directory do not depend on the machine. The full binary (the
//! default `episode-serve` feature) is the one documented.
#![cfg(feature = "episode-serve")]
use std::path::PathBuf;
use std::process::Command;

const REGENERATE: &str = "UPDATE_CLI_REFERENCE=1 cargo test -p libero-agent --test cli_reference";

fn reference_path() -> PathBuf {
    libero_testkit::repo_root().join("docs/cli.md")
}

/// `libero-agent <path…> --help`.
fn help(path: &[String]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_libero-agent"))
        .args(path)
        .arg("--help")
        .env_clear()
        .env("HOME", "/home/user")
        .env("PATH", "/usr/bin:/bin")
        .output()
        .expect("run libero-agent --help");
    assert!(
        out.status.success(),
        "libero-agent {} --help failed: {}",
        path.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("help is UTF-8")
}

/// The subcommands a help text lists under `Commands:` (clap's layout: two spaces, the name, the description),
/// without clap's own `help`.
fn subcommands(help: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut inside = false;
    for line in help.lines() {
        if line.trim_end() == "Commands:" {
            inside = true;
            continue;
        }
        if inside {
            if line.trim().is_empty() || !line.starts_with("  ") {
                break;
            }
            // A description continued on the next line is indented deeper than the names.
            if line.starts_with("   ") {
                continue;
            }
            let name = line.split_whitespace().next().unwrap_or_default();
            if !name.is_empty() && name != "help" {
                out.push(name.to_string());
            }
        }
    }
    out
}

/// The reference: one section per command, depth first in the order the binary lists them.
fn generate() -> String {
    let mut out = String::from(
        "# `libero-agent` command-line reference\n\n\
         Generated from the binary's own `--help` by `server/app/tests/cli_reference.rs`, which fails when this file \
         differs from the binary; do not edit it by hand. Regenerate with:\n\n\
         ```sh\n",
    );
    out.push_str(REGENERATE);
    out.push_str(
        "\n```\n\n\
         What the commands are for, with examples and measured figures: [commands.md](commands.md).\n",
    );
    let mut stack: Vec<Vec<String>> = vec![Vec::new()];
    let mut sections = Vec::new();
    while let Some(path) = stack.pop() {
        let text = help(&path);
        let children = subcommands(&text);
        sections.push((path.clone(), text));
        for child in children.into_iter().rev() {
            let mut next = path.clone();
            next.push(child);
            stack.push(next);
        }
    }
    for (path, text) in sections {
        let title = if path.is_empty() { "libero-agent".to_string() } else { format!("libero-agent {}", path.join(" ")) };
        out.push_str(&format!("\n## `{title}`\n\n```text\n{}\n```\n", text.trim_end()));
    }
    out
}

/// The first differing lines of two texts, as `-` (the file) and `+` (the binary) lines with their numbers.
fn diff(file: &str, binary: &str) -> String {
    let a: Vec<&str> = file.lines().collect();
    let b: Vec<&str> = binary.lines().collect();
    let mut out = Vec::new();
    let mut shown = 0;
    for i in 0..a.len().max(b.len()) {
        let (x, y) = (a.get(i), b.get(i));
        if x != y {
            if let Some(x) = x {
                out.push(format!("-{:>5}: {x}", i + 1));
            }
            if let Some(y) = y {
                out.push(format!("+{:>5}: {y}", i + 1));
            }
            shown += 1;
            if shown == 20 {
                out.push("… (more differences)".into());
                break;
            }
        }
    }
    out.join("\n")
}

#[test]
fn docs_cli_md_is_the_binarys_help() {
    let generated = generate();
    assert!(generated.contains("## `libero-agent serve`") && generated.contains("## `libero-agent bench mcp`"), "{generated}");
    let path = reference_path();
    if std::env::var_os("UPDATE_CLI_REFERENCE").is_some() {
        std::fs::write(&path, &generated).unwrap_or_else(|e| panic!("write {}: {e}", path.display()));
        return;
    }
    let current = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        current == generated,
        "docs/cli.md differs from `libero-agent --help` of this build (- the file, + the binary):\n{}\n\n\
         Regenerate it with:\n    {REGENERATE}",
        diff(&current, &generated)
    );
}

#[test]
fn the_command_list_is_read_from_claps_layout() {
    let text = "Usage: libero-agent <COMMAND>\n\nCommands:\n  sim     Simulation tools\n  render  Render RGB, depth\n          and more\n  help    Print this message\n\nOptions:\n  -h, --help  Print help\n";
    assert_eq!(subcommands(text), ["sim", "render"]);
    assert_eq!(diff("a\nb\n", "a\nc\n"), "-    2: b\n+    2: c");
}

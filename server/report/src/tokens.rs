//! Tokens with where each figure came from, for every row of `report` and the Results page. A rollout's `usage`
//! says its source (`usage.source`): the runner's model-API gateway (which the agent cannot write), the harness's
//! own stdout (only without the sandbox), or neither; records written before sources were recorded have none, and
//! are shown as "source not recorded", never guessed. A row counts every episode (INVALID ones included, as the
//! paper averages over all episodes of a table, and said so; INTERRUPTED rollouts, cut off by a stopped batch, are
//! left out), averages the figures of those with usage, and says how many came from where.
use std::fmt::Write as _;

use serde::Serialize;

use crate::batch::RolloutRecord;
use crate::usage::{SOURCE_GATEWAY, SOURCE_NONE, SOURCE_STDOUT};

/// A record with usage but no `source` (written before sources were recorded).
pub const NOT_RECORDED: &str = "not_recorded";

/// Where a rollout's figures came from: [`SOURCE_GATEWAY`], [`SOURCE_STDOUT`], [`SOURCE_NONE`] (also a rollout
/// that never measured any) or [`NOT_RECORDED`].
pub fn source_of(r: &RolloutRecord) -> &'static str {
    match &r.usage {
        None => SOURCE_NONE,
        Some(u) => match u.source.as_deref() {
            Some(SOURCE_GATEWAY) => SOURCE_GATEWAY,
            Some(SOURCE_STDOUT) => SOURCE_STDOUT,
            Some(SOURCE_NONE) => SOURCE_NONE,
            _ => NOT_RECORDED,
        },
    }
}

/// The one-letter mark of a source in per-task cells: `G` gateway, `S` harness stdout, `–` none, `?` not recorded.
pub fn mark(source: &str) -> &'static str {
    match source {
        SOURCE_GATEWAY => "G",
        SOURCE_STDOUT => "S",
        SOURCE_NONE => "–",
        _ => "?",
    }
}

/// The legend of [`mark`], printed under every table that uses the marks.
pub const LEGEND: &str = "Token sources: G the runner's model-API gateway (the agent cannot write it), S the harness's own stdout \
(runs without the sandbox), – no usage reported, ? source not recorded (a record from before sources were recorded). \
Input tokens follow the provider: OpenAI-style APIs count cached input inside them, Anthropic's beside them.";

/// One rollout's figures and their source (`/api/results` episodes, the report's per-rollout lines).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RolloutTokens {
    pub total: Option<u64>,
    pub input: Option<u64>,
    pub output: Option<u64>,
    /// Cached input (`cache_read_input_tokens`).
    pub cached: Option<u64>,
    pub source: &'static str,
}

impl RolloutTokens {
    pub fn of(r: &RolloutRecord) -> Self {
        let source = source_of(r);
        let u = r.usage.as_ref().filter(|_| source != SOURCE_NONE);
        Self {
            total: u.and_then(|u| u.total_tokens),
            input: u.and_then(|u| u.input_tokens),
            output: u.and_then(|u| u.output_tokens),
            cached: u.and_then(|u| u.cache_read_input_tokens),
            source,
        }
    }

    /// `8,610 G`, or `– ` with the mark alone when there is no figure.
    pub fn short(&self) -> String {
        match self.total {
            Some(t) => format!("{} {}", thousands(t as f64), mark(self.source)),
            None => mark(self.source).to_owned(),
        }
    }
}

/// How many of a row's rollouts took their figures from each source.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct SourceCounts {
    pub model_api_gateway: usize,
    pub harness_stdout: usize,
    pub unavailable: usize,
    pub not_recorded: usize,
}

/// Figures of one side of a disagreement.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Figures {
    pub input: Option<u64>,
    pub output: Option<u64>,
    pub total: Option<u64>,
}

/// A rollout whose harness printed other figures on stdout than the gateway recorded (the gateway's count).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Disagreement {
    pub rollout_id: String,
    pub gateway: Figures,
    pub harness_stdout: Figures,
}

/// A row's tokens: means over its valid rollouts with usage, and where the figures came from.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct TokenSummary {
    pub mean_total: Option<f64>,
    pub mean_input: Option<f64>,
    pub mean_cached: Option<f64>,
    pub mean_output: Option<f64>,
    pub rollouts_with_usage: usize,
    /// Episodes of the row: every rollout but INTERRUPTED ones, INVALID included.
    pub rollouts: usize,
    /// INVALID rollouts among `rollouts` (inside the means when they have usage).
    pub invalid_included: usize,
    pub sources: SourceCounts,
    pub stdout_disagrees: Vec<Disagreement>,
}

fn mean(xs: impl Iterator<Item = u64>) -> Option<f64> {
    let (n, sum) = xs.fold((0u64, 0f64), |(n, s), x| (n + 1, s + x as f64));
    (n > 0).then(|| sum / n as f64)
}

impl TokenSummary {
    /// Over `records`' episodes: INVALID rollouts included (the paper averages over all episodes), INTERRUPTED ones
    /// left out (as the metrics' time average, [`libero_metrics::is_episode`]).
    pub fn of<'a>(records: impl IntoIterator<Item = &'a RolloutRecord>) -> Self {
        let valid: Vec<&RolloutRecord> = records.into_iter().filter(|r| libero_metrics::is_episode(r.outcome)).collect();
        let invalid_included = valid.iter().filter(|r| r.outcome == libero_metrics::Outcome::Invalid).count();
        let mut s = Self { rollouts: valid.len(), invalid_included, ..Self::default() };
        let figures: Vec<RolloutTokens> = valid.iter().map(|r| RolloutTokens::of(r)).collect();
        for f in &figures {
            match f.source {
                SOURCE_GATEWAY => s.sources.model_api_gateway += 1,
                SOURCE_STDOUT => s.sources.harness_stdout += 1,
                SOURCE_NONE => s.sources.unavailable += 1,
                _ => s.sources.not_recorded += 1,
            }
        }
        let with: Vec<&RolloutTokens> = figures.iter().filter(|f| f.total.is_some()).collect();
        s.rollouts_with_usage = with.len();
        s.mean_total = mean(with.iter().filter_map(|f| f.total));
        s.mean_input = mean(with.iter().filter_map(|f| f.input));
        s.mean_cached = mean(with.iter().filter_map(|f| f.cached));
        s.mean_output = mean(with.iter().filter_map(|f| f.output));
        for r in &valid {
            if let Some(u) = &r.usage
                && let Some(h) = u.harness_stdout.as_ref().filter(|h| !h.agrees)
            {
                s.stdout_disagrees.push(Disagreement {
                    rollout_id: r.rollout_id.clone(),
                    gateway: Figures { input: u.input_tokens, output: u.output_tokens, total: u.total_tokens },
                    harness_stdout: Figures { input: h.input_tokens, output: h.output_tokens, total: h.total_tokens },
                });
            }
        }
        s
    }

    /// Where the figures came from, e.g. `gateway 90/90`, `gateway 58, stdout 2; 30 without usage`, `no usage: 90
    /// rollouts`, with `; stdout disagrees: 1` when the harness printed other figures than the gateway recorded, and
    /// `; 2 INVALID incl.` when INVALID episodes are among those averaged.
    pub fn sources_text(&self) -> String {
        if self.rollouts == 0 {
            return "no episodes".into();
        }
        let invalid = if self.invalid_included > 0 { format!("; {} INVALID incl.", self.invalid_included) } else { String::new() };
        if self.rollouts_with_usage == 0 {
            let unrecorded = if self.sources.not_recorded > 0 { format!(", {} with the source not recorded", self.sources.not_recorded) } else { String::new() };
            return format!("no usage: {} rollout{}{unrecorded}{invalid}", self.rollouts, if self.rollouts == 1 { "" } else { "s" });
        }
        let c = &self.sources;
        let parts: Vec<String> = [("gateway", c.model_api_gateway), ("stdout", c.harness_stdout), ("source not recorded", c.not_recorded)]
            .into_iter()
            .filter(|(_, n)| *n > 0)
            .map(|(k, n)| format!("{k} {n}"))
            .collect();
        let mut o = if parts.len() == 1 && self.rollouts_with_usage == self.rollouts {
            format!("{}/{}", parts[0], self.rollouts)
        } else {
            parts.join(", ")
        };
        let without = self.rollouts - self.rollouts_with_usage;
        if without > 0 {
            let _ = write!(o, "; {without} without usage");
        }
        if !self.stdout_disagrees.is_empty() {
            let _ = write!(o, "; stdout disagrees: {}", self.stdout_disagrees.len());
        }
        o.push_str(&invalid);
        o
    }

    /// The mean total with its sources: `8,610 (gateway 90/90)`, or `– (no usage: 90 rollouts)`, never 0.
    pub fn text(&self) -> String {
        match self.mean_total {
            Some(t) => format!("{} ({})", thousands(t), self.sources_text()),
            None => format!("– ({})", self.sources_text()),
        }
    }

    /// Table 1's cell in millions: `0.01M (gateway 2/2)`.
    pub fn millions_text(&self) -> String {
        match self.mean_total {
            Some(t) => format!("{:.2}M ({})", t / 1e6, self.sources_text()),
            None => format!("– ({})", self.sources_text()),
        }
    }

    /// `model_api_gateway=2 harness_stdout=0 unavailable=0 not_recorded=0` (one CSV field, no commas).
    pub fn sources_field(&self) -> String {
        let c = &self.sources;
        format!(
            "{SOURCE_GATEWAY}={} {SOURCE_STDOUT}={} {SOURCE_NONE}={} {NOT_RECORDED}={}",
            c.model_api_gateway, c.harness_stdout, c.unavailable, c.not_recorded
        )
    }
}

/// `8610.4` as `8,610`.
pub fn thousands(x: f64) -> String {
    let digits = format!("{:.0}", x.max(0.0));
    let mut o = String::new();
    for (i, ch) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i) % 3 == 0 {
            o.push(',');
        }
        o.push(ch);
    }
    o
}

/// A task's rollouts as `8,610 G · 9,020 S`, by repetition.
pub fn per_rollout_text<'a>(records: impl IntoIterator<Item = &'a RolloutRecord>) -> String {
    let mut rs: Vec<&RolloutRecord> = records.into_iter().collect();
    rs.sort_by_key(|r| r.repetition);
    rs.iter().map(|r| RolloutTokens::of(r).short()).collect::<Vec<_>>().join(" · ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thousands_are_grouped() {
        assert_eq!(thousands(8610.4), "8,610");
        assert_eq!(thousands(999.0), "999");
        assert_eq!(thousands(1_234_567.0), "1,234,567");
        assert_eq!(thousands(0.0), "0");
    }
}

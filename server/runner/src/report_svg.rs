//! Figure 3 drawn as standalone SVG (no script, no external font or library), the same text for `report --figures
//! DIR` and inline on the dashboard's Results page: local opening success per SCR bin with 95 % Wilson whiskers, one
//! bar per agent and condition, and each agent's mean SCR with Pearson's r.
use std::fmt::Write as _;

use libero_metrics::ScrBin;

use crate::report::tables::ContactLine;

/// Series colours (colour-blind safe, Okabe–Ito).
const PALETTE: [&str; 8] = ["#0072B2", "#E69F00", "#009E73", "#D55E00", "#CC79A7", "#56B4E9", "#F0E442", "#000000"];

/// `text` as SVG character data or attribute value.
pub fn esc(text: &str) -> String {
    text.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;").replace('\'', "&#39;")
}

fn open(o: &mut String, width: f64, height: f64, title: &str) {
    let _ = write!(
        o,
        r##"<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {width} {height}" width="{width}" height="{height}" role="img" aria-label="{t}" font-family="sans-serif" font-size="12"><title>{t}</title><rect width="100%" height="100%" fill="#fff"/>"##,
        t = esc(title)
    );
    let _ = write!(o, r#"<text x="{:.1}" y="18" text-anchor="middle" font-size="14" font-weight="bold">{}</text>"#, width / 2.0, esc(title));
}

/// Local opening success (%) per SCR bin, grouped bars with Wilson whiskers and `k/n` above each bar.
pub fn success_by_bin(lines: &[ContactLine]) -> String {
    let (left, right, top, plot_h, group_w) = (56.0, 16.0, 46.0, 220.0, 150.0);
    let width = left + right + group_w * ScrBin::ALL.len() as f64;
    let legend_top = top + plot_h + 44.0;
    let height = legend_top + 18.0 * lines.len().max(1) as f64 + 8.0;
    let mut o = String::new();
    open(&mut o, width, height, "Figure 3: local opening success by sustained-contact ratio");
    let y = |rate: f64| top + plot_h * (1.0 - rate);
    for tick in [0.0, 0.25, 0.5, 0.75, 1.0] {
        let _ = write!(
            o,
            r##"<line x1="{left}" x2="{:.1}" y1="{y:.1}" y2="{y:.1}" stroke="#ddd"/><text x="{:.1}" y="{:.1}" text-anchor="end">{:.0}%</text>"##,
            width - right,
            left - 6.0,
            y(tick) + 4.0,
            100.0 * tick,
            y = y(tick)
        );
    }
    let _ = write!(
        o,
        r#"<text transform="translate(14 {:.1}) rotate(-90)" text-anchor="middle">local opening success</text>"#,
        top + plot_h / 2.0
    );
    let n = lines.len().max(1) as f64;
    let bar_w = (group_w * 0.8 / n).min(40.0);
    for (g, bin) in ScrBin::ALL.iter().enumerate() {
        let gx = left + group_w * g as f64;
        let start = gx + (group_w - bar_w * n) / 2.0;
        for (k, line) in lines.iter().enumerate() {
            let colour = PALETTE[k % PALETTE.len()];
            let x = start + bar_w * k as f64;
            let cx = x + bar_w / 2.0;
            let Some(b) = line.summary.bins.iter().find(|b| b.bin == *bin) else { continue };
            let p = &b.local_success;
            let label = format!("{}/{}", p.successes, p.trials);
            match (p.rate, p.wilson_low, p.wilson_high) {
                (Some(rate), Some(lo), Some(hi)) => {
                    let _ = write!(
                        o,
                        r#"<rect x="{:.1}" y="{:.1}" width="{:.1}" height="{:.1}" fill="{colour}"><title>{}: SCR {}: {label} opened, 95% Wilson [{:.1}%, {:.1}%]</title></rect>"#,
                        x + 1.0,
                        y(rate),
                        bar_w - 2.0,
                        plot_h * rate,
                        esc(&line.label()),
                        esc(bin.label()),
                        100.0 * lo,
                        100.0 * hi
                    );
                    let _ = write!(
                        o,
                        r##"<path d="M{cx:.1} {:.1}V{:.1}M{:.1} {:.1}h{:.1}M{:.1} {:.1}h{:.1}" stroke="#333" fill="none"/>"##,
                        y(lo),
                        y(hi),
                        cx - 4.0,
                        y(lo),
                        8.0,
                        cx - 4.0,
                        y(hi),
                        8.0
                    );
                    let _ = write!(o, r#"<text x="{cx:.1}" y="{:.1}" text-anchor="middle" font-size="10">{label}</text>"#, y(hi) - 4.0);
                }
                _ => {
                    let _ = write!(o, r##"<text x="{cx:.1}" y="{:.1}" text-anchor="middle" font-size="10" fill="#888">0/0</text>"##, y(0.0) - 4.0);
                }
            }
        }
        let _ = write!(
            o,
            r#"<text x="{:.1}" y="{:.1}" text-anchor="middle">SCR {}</text>"#,
            gx + group_w / 2.0,
            top + plot_h + 18.0,
            esc(bin.label())
        );
    }
    let _ = write!(o, r##"<line x1="{left}" x2="{:.1}" y1="{:.1}" y2="{:.1}" stroke="#333"/>"##, width - right, y(0.0), y(0.0));
    for (k, line) in lines.iter().enumerate() {
        let ly = legend_top + 18.0 * k as f64;
        let _ = write!(
            o,
            r#"<rect x="{left}" y="{:.1}" width="12" height="12" fill="{}"/><text x="{:.1}" y="{:.1}">{} — {} operations, r = {}</text>"#,
            ly - 10.0,
            PALETTE[k % PALETTE.len()],
            left + 18.0,
            ly,
            esc(&line.label()),
            line.summary.operations,
            line.summary.pearson_r.map(|r| format!("{r:.2}")).unwrap_or_else(|| "—".into())
        );
    }
    if lines.is_empty() {
        let _ = write!(o, r##"<text x="{left}" y="{legend_top:.1}" fill="#888">no opening operation</text>"##);
    }
    o.push_str("</svg>\n");
    o
}

/// Each agent's (and condition's) mean SCR as a horizontal bar, with the number of operations and Pearson's r.
pub fn mean_scr(lines: &[ContactLine]) -> String {
    let (label_w, bar_max, top, row_h) = (300.0, 300.0, 34.0, 26.0);
    let width = label_w + bar_max + 190.0;
    let height = top + row_h * lines.len().max(1) as f64 + 30.0;
    let mut o = String::new();
    open(&mut o, width, height, "Figure 3: mean sustained-contact ratio of opening operations");
    for tick in [0.0, 25.0, 50.0, 75.0, 100.0] {
        let x = label_w + bar_max * tick / 100.0;
        let _ = write!(
            o,
            r##"<line x1="{x:.1}" x2="{x:.1}" y1="{top}" y2="{:.1}" stroke="#ddd"/><text x="{x:.1}" y="{:.1}" text-anchor="middle">{tick:.0}%</text>"##,
            height - 26.0,
            height - 12.0
        );
    }
    for (k, line) in lines.iter().enumerate() {
        let y = top + row_h * k as f64;
        let s = &line.summary;
        let mean = s.mean_scr_percent.unwrap_or(0.0);
        let _ = write!(
            o,
            r#"<text x="{:.1}" y="{:.1}" text-anchor="end">{}</text><rect x="{label_w}" y="{:.1}" width="{:.1}" height="{:.1}" fill="{}"/><text x="{:.1}" y="{:.1}">{} · n = {} · r = {}</text>"#,
            label_w - 8.0,
            y + row_h / 2.0 + 4.0,
            esc(&line.label()),
            y + 4.0,
            bar_max * mean / 100.0,
            row_h - 8.0,
            PALETTE[k % PALETTE.len()],
            label_w + bar_max * mean / 100.0 + 6.0,
            y + row_h / 2.0 + 4.0,
            s.mean_scr_percent.map(|m| format!("{m:.1}%")).unwrap_or_else(|| "—".into()),
            s.operations,
            s.pearson_r.map(|r| format!("{r:.2}")).unwrap_or_else(|| "—".into())
        );
    }
    if lines.is_empty() {
        let _ = write!(o, r##"<text x="{label_w}" y="{:.1}" fill="#888">no opening operation</text>"##, top + 16.0);
    }
    o.push_str("</svg>\n");
    o
}

#[cfg(test)]
mod tests {
    use libero_metrics::{OpeningOperation, summarize_contact};

    use super::*;

    fn line(agent: &str, ops: &[(f64, bool)]) -> ContactLine {
        let ops: Vec<OpeningOperation> = ops
            .iter()
            .map(|&(scr, opened)| OpeningOperation { task: "T16".into(), stage_name: None, scr_percent: scr, exec_steps: 50, opened })
            .collect();
        ContactLine { agent: agent.into(), condition: "L3, none".into(), summary: summarize_contact(&ops), opening_operations: ops, rollouts_without_record: 0 }
    }

    #[test]
    fn the_bin_plot_draws_one_bar_per_series_and_nonempty_bin_with_escaped_labels() {
        let lines = [line("codex/<m&1>", &[(0.0, false), (30.0, true)]), line("claude/x", &[(5.0, true)])];
        let svg = success_by_bin(&lines);
        assert!(svg.starts_with("<svg xmlns=\"http://www.w3.org/2000/svg\"") && svg.trim_end().ends_with("</svg>"));
        assert_eq!(svg.matches("<rect x=").count() - 2, 3, "three non-empty (series, bin) bars besides the legend keys");
        assert!(svg.contains("codex/&lt;m&amp;1&gt;") && !svg.contains("<m&1>"), "labels are escaped");
        assert!(svg.contains(">1/1<") && svg.contains(">0/1<") && svg.contains(">0/0<"));
        let mean = mean_scr(&lines);
        assert!(mean.contains("15.0% · n = 2") && mean.contains("5.0% · n = 1"), "{mean}");
    }
}

//! Figure 3 drawn as one standalone SVG of two panels (no script, no external font or library), the same text for
//! `report --figures DIR` and inline on the dashboard's Results page: (a) each agent's mean SCR, (b) the local opening
//! success per SCR bin over every agent's operations, with 95 % Wilson whiskers, `k/n` and Pearson's r.
use std::fmt::Write as _;

use crate::figure3::Figure3Data;

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

/// A horizontal grid line at `y` across `[x1, x2]` with its label on the left.
fn grid_y(o: &mut String, x1: f64, x2: f64, y: f64, label: &str) {
    let _ = write!(
        o,
        r##"<line x1="{x1:.1}" x2="{x2:.1}" y1="{y:.1}" y2="{y:.1}" stroke="#ddd"/><text x="{:.1}" y="{:.1}" text-anchor="end">{label}</text>"##,
        x1 - 6.0,
        y + 4.0
    );
}

/// Figure 3: (a) mean SCR per agent as horizontal bars; (b) local opening success per SCR bin, pooled, as bars with
/// Wilson whiskers and `k/n` above each, Pearson's r in the panel's title.
pub fn figure3(d: &Figure3Data) -> String {
    let f = &d.figure;
    let top = 70.0;
    // (a): agent labels, bars up to the axis maximum (the largest mean rounded up to 20 %, at least 20 %: ticks of 5 %
    // multiples)
    let (a_label_w, a_bar_w, row_h) = (200.0, 220.0, 26.0);
    let a_left = 16.0 + a_label_w;
    let a_w = a_label_w + a_bar_w + 120.0;
    let max_mean = f.agents.iter().filter_map(|a| a.mean_scr_percent).fold(0.0_f64, f64::max);
    let a_max = ((max_mean / 20.0).ceil() * 20.0).clamp(20.0, 100.0);
    // (b): four bins
    let (b_axis, plot_h, group_w, bar_w) = (56.0, 220.0, 90.0, 44.0);
    let b_left = 16.0 + a_w + 40.0 + b_axis;
    let width = b_left + group_w * 4.0 + 16.0;
    let a_h = row_h * f.agents.len().max(1) as f64 + 44.0;
    let height = top + a_h.max(plot_h + 40.0) + 16.0;
    let mut o = String::new();
    open(&mut o, width, height, "Figure 3: sustained-contact ratio (SCR) of opening operations");
    let r = f.pooled.pearson_r.map(|r| format!("{r:.2}")).unwrap_or_else(|| "—".into());
    let _ = write!(
        o,
        r#"<text x="16" y="46" font-weight="bold">(a) mean SCR per agent</text><text x="{:.1}" y="46" font-weight="bold">(b) local opening success by SCR bin, pooled: n = {}, r = {}</text>"#,
        b_left - b_axis,
        f.pooled.operations,
        esc(&r)
    );

    // (a)
    let ax = |scr: f64| a_left + a_bar_w * scr / a_max;
    let a_bottom = top + row_h * f.agents.len().max(1) as f64;
    for k in 0..=4 {
        let v = a_max * k as f64 / 4.0;
        let _ = write!(
            o,
            r##"<line x1="{x:.1}" x2="{x:.1}" y1="{top}" y2="{a_bottom:.1}" stroke="#ddd"/><text x="{x:.1}" y="{:.1}" text-anchor="middle">{v:.0}%</text>"##,
            a_bottom + 16.0,
            x = ax(v)
        );
    }
    let _ = write!(
        o,
        r#"<text x="{:.1}" y="{:.1}" text-anchor="middle">mean SCR of the agent's entered opening operations</text>"#,
        a_left + a_bar_w / 2.0,
        a_bottom + 34.0
    );
    for (k, a) in f.agents.iter().enumerate() {
        let y = top + row_h * k as f64;
        let mean = a.mean_scr_percent.unwrap_or(0.0);
        let _ = write!(
            o,
            r#"<text x="{:.1}" y="{:.1}" text-anchor="end">{}</text><rect x="{a_left:.1}" y="{:.1}" width="{:.1}" height="{:.1}" fill="{}"><title>{}: mean SCR {mean:.2}% over {} operations</title></rect><text x="{:.1}" y="{:.1}">{mean:.1}% (n = {})</text>"#,
            a_left - 8.0,
            y + row_h / 2.0 + 4.0,
            esc(&a.agent),
            y + 4.0,
            ax(mean) - a_left,
            row_h - 8.0,
            PALETTE[k % PALETTE.len()],
            esc(&a.agent),
            a.operations,
            ax(mean) + 6.0,
            y + row_h / 2.0 + 4.0,
            a.operations
        );
    }
    if f.agents.is_empty() {
        let _ = write!(o, r##"<text x="{a_left:.1}" y="{:.1}" fill="#888">no entered opening operation</text>"##, top + 16.0);
    }

    // (b)
    let y = |rate: f64| top + plot_h * (1.0 - rate);
    let b_right = b_left + group_w * 4.0;
    for tick in [0.0, 0.25, 0.5, 0.75, 1.0] {
        grid_y(&mut o, b_left, b_right, y(tick), &format!("{:.0}%", 100.0 * tick));
    }
    let _ = write!(
        o,
        r#"<text transform="translate({:.1} {:.1}) rotate(-90)" text-anchor="middle">local opening success</text>"#,
        b_left - b_axis + 10.0,
        top + plot_h / 2.0
    );
    for (g, b) in f.pooled.bins.iter().enumerate() {
        let gx = b_left + group_w * g as f64;
        let cx = gx + group_w / 2.0;
        let p = &b.local_success;
        let label = format!("{}/{}", p.successes, p.trials);
        match (p.rate, p.wilson_low, p.wilson_high) {
            (Some(rate), Some(lo), Some(hi)) => {
                let _ = write!(
                    o,
                    r##"<rect x="{:.1}" y="{:.1}" width="{bar_w:.1}" height="{:.1}" fill="#0072B2"><title>SCR {}: {label} opened, 95% Wilson [{:.1}%, {:.1}%]</title></rect><path d="M{cx:.1} {:.1}V{:.1}M{:.1} {:.1}h8M{:.1} {:.1}h8" stroke="#333" fill="none"/><text x="{cx:.1}" y="{:.1}" text-anchor="middle" font-size="11">{label}</text>"##,
                    cx - bar_w / 2.0,
                    y(rate),
                    plot_h * rate,
                    esc(&b.label),
                    100.0 * lo,
                    100.0 * hi,
                    y(lo),
                    y(hi),
                    cx - 4.0,
                    y(lo),
                    cx - 4.0,
                    y(hi),
                    y(hi) - 4.0
                );
            }
            _ => {
                let _ = write!(o, r##"<text x="{cx:.1}" y="{:.1}" text-anchor="middle" font-size="11" fill="#888">0/0</text>"##, y(0.0) - 4.0);
            }
        }
        let _ = write!(o, r#"<text x="{cx:.1}" y="{:.1}" text-anchor="middle">SCR {}</text>"#, top + plot_h + 18.0, esc(&b.label));
    }
    let _ = write!(o, r##"<line x1="{b_left:.1}" x2="{b_right:.1}" y1="{:.1}" y2="{:.1}" stroke="#333"/>"##, y(0.0), y(0.0));
    o.push_str("</svg>\n");
    o
}

#[cfg(test)]
mod tests {
    use libero_metrics::OpeningOperation;

    use super::*;

    fn op(agent: &str, runs: &[u64], opened: bool) -> OpeningOperation {
        OpeningOperation { entered: true, opened, ..OpeningOperation::new(agent, "T21", None, 50, Some(runs.to_vec())) }
    }

    #[test]
    fn one_svg_draws_both_panels_with_escaped_labels() {
        let ops = vec![op("codex/<m&1>", &[], false), op("codex/<m&1>", &[15], true), op("claude/x", &[5], true)];
        let svg = figure3(&Figure3Data::new(ops, 3, 0));
        assert!(svg.starts_with("<svg xmlns=\"http://www.w3.org/2000/svg\"") && svg.trim_end().ends_with("</svg>"));
        assert_eq!(svg.matches("<svg").count(), 1, "one figure");
        assert!(svg.contains("(a) mean SCR per agent") && svg.contains("(b) local opening success by SCR bin, pooled: n = 3"));
        assert!(svg.contains("codex/&lt;m&amp;1&gt;") && !svg.contains("<m&1>"), "labels are escaped");
        // (a): codex 0 and 30 → 15.0 %, claude 10.0 %; (b): SCR 0 0/1, (0,10%] 1/1, (10,25%] empty, >25% 1/1
        assert!(svg.contains("15.0% (n = 2)") && svg.contains("10.0% (n = 1)"), "{svg}");
        assert!(svg.contains(">0/1<") && svg.contains(">1/1<") && svg.contains(">0/0<"), "{svg}");
        assert_eq!(svg.matches("fill=\"#0072B2\"><title>SCR").count(), 3, "three non-empty bins");
    }
}

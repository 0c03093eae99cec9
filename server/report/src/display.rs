//! Text cells every format shares: the display table (Markdown, LaTeX, the Results page) and the cell texts of CSV,
//! shares and correlations, for the tables and Figure 3 alike.
use libero_metrics::Proportion;

/// One table as text cells: what Markdown, LaTeX and the Results page show.
#[derive(Debug, Clone, PartialEq)]
pub struct DisplayTable {
    /// `table-2`, `figure-3`, `appendix-e-short-horizon`, … (the page's element id).
    pub id: String,
    pub title: String,
    /// What the numbers mean and where they come from (the whole body when `rows` is empty).
    pub note: String,
    pub heads: Vec<String>,
    pub rows: Vec<Vec<String>>,
}

pub(crate) fn strings<const N: usize>(heads: [&str; N]) -> Vec<String> {
    heads.map(str::to_owned).to_vec()
}

/// `k/n = p%`.
pub(crate) fn share(p: &Proportion) -> String {
    match p.rate {
        Some(r) => format!("{}/{} = {:.1}%", p.successes, p.trials, 100.0 * r),
        None => "—".into(),
    }
}

pub(crate) fn r_text(r: Option<f64>) -> String {
    r.map(|r| format!("{r:.3}")).unwrap_or_else(|| "—".into())
}

/// A CSV field, quoted where it needs to be.
pub(crate) fn field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) { format!("\"{}\"", s.replace('"', "\"\"")) } else { s.to_owned() }
}

/// A fraction in [0, 1] as a percentage with 4 decimals, empty when unknown.
pub(crate) fn p4(x: Option<f64>) -> String {
    x.map(|v| format!("{:.4}", 100.0 * v)).unwrap_or_default()
}

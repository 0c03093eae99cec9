//! `libero-agent report BATCH… [--format markdown|csv|json|latex] [--table …] [--figures DIR]`: the paper's tables
//! from batch directories (or a store's batches), computed and printed by `libero-report`. Here only what the
//! report crate does not link: the command line, reading batches from a store, and the catalog's task facts.
use std::path::PathBuf;

use anyhow::bail;
use libero_report::batch::load_batch;
use libero_report::tables::{self, TableChoice};
use libero_report::{batch_reps, csv, default_reps, latex, markdown, report_json, rows};

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    #[value(alias = "md")]
    Markdown,
    Csv,
    Json,
    Latex,
}

#[derive(clap::Args, Debug)]
pub struct ReportArgs {
    /// Batch directories written by `libero-agent run`; with `--store`, batch names in that store.
    #[arg(required = true)]
    pub batches: Vec<PathBuf>,
    /// Read the batches from this store (`sqlite://PATH`, `postgres://…`) as `run --store` wrote them, by name.
    #[arg(long, value_name = "URL")]
    pub store: Option<String>,
    #[arg(long, value_enum, default_value = "markdown")]
    pub format: Format,
    /// Rollouts per task the stable rule needs (default: the first batch's own `--reps`, as the Results page uses).
    #[arg(long)]
    pub reps: Option<usize>,
    /// Which table Markdown, CSV and LaTeX print (JSON always holds every one): all, table1…table4, figure3 (its data),
    /// appendix (the per-task tables of Appendix E, wide).
    #[arg(long, value_enum, default_value = "all")]
    pub table: TableChoice,
    /// Also write Figure 3 to this folder: one SVG with its two panels (mean SCR per agent; local opening success by
    /// SCR bin, pooled) and their data (CSV, JSON).
    #[arg(long, value_name = "DIR")]
    pub figures: Option<PathBuf>,
}

pub fn run(args: ReportArgs) -> anyhow::Result<()> {
    if args.reps == Some(0) {
        bail!("--reps must be at least 1");
    }
    let batches = match &args.store {
        Some(url) => {
            let names: Vec<String> = args.batches.iter().map(|n| n.to_string_lossy().into_owned()).collect();
            crate::batch::load_batches_from_store(url, &names)?
        }
        None => args.batches.iter().map(|d| load_batch(d)).collect::<Result<Vec<_>, _>>()?,
    };
    let reps = args.reps.unwrap_or_else(|| default_reps(&batches));
    if args.reps.is_none() && batches.iter().filter_map(batch_reps).any(|n| n != reps) {
        eprintln!("note: the batches were run with different --reps; the stable rule uses {reps} (the first batch's); pass --reps N to choose");
    }
    let facts = libero_tasks::catalog::task_facts();
    let out = match args.format {
        Format::Markdown => markdown(&batches, reps, args.table, facts),
        Format::Csv => csv(&batches, reps, args.table, facts),
        Format::Json => serde_json::to_string_pretty(&report_json(&batches, reps, facts))? + "\n",
        Format::Latex => latex(&batches, reps, args.table, facts),
    };
    print!("{out}");
    if let Some(dir) = &args.figures {
        let paper = tables::paper_tables(&batches, &rows(&batches, reps), reps, facts);
        for path in tables::write_figures(&paper, dir).map_err(|e| anyhow::anyhow!("cannot write figures to {}: {e}", dir.display()))? {
            eprintln!("wrote {}", path.display());
        }
    }
    Ok(())
}

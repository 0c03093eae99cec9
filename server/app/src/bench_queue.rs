//! `libero-agent bench queue`: the queue's cost and its scale-out on this machine, in one run.
//!
//! - **Claim latency**: `n` claimers (threads, each with the store's pool) drain a synthetic batch, each claim
//!   followed by its finish; every claim call is timed (p50/p95 ms) for each claimer count.
//! - **Rollouts per hour**: a real batch (T14 with the reference agent, private video on) is queued and drained by
//!   `n` `libero-agent worker` processes (`--exit-when-idle`), timed from their start to the batch's end, for each
//!   worker count; `speedup` is each count's rate over the first's.
//!
//! The store is `--store` (a PostgreSQL URL for the figures that matter) or a throwaway embedded SQLite file.
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use libero_records::batch_doc::BatchDoc;
use libero_records::records::Outcome;
use libero_store::Store;
use serde::Serialize;
use serde_json::{Value, json};

use libero_runner::batch::BatchSettings;
use libero_runner::queue::enqueue;
use libero_runner::schedule::{Experiment, plan};

/// One worker count's real batch, as the output's `rollouts` lists it.
#[derive(Serialize)]
struct Rate {
    workers: usize,
    rollouts: u32,
    elapsed_s: f64,
    rollouts_per_hour: f64,
    /// The batch document's `outcomes` (ended rollouts per class).
    outcomes: Value,
    /// `rollouts_per_hour` over the first count's.
    speedup: f64,
}

#[derive(clap::Args, Debug, Clone)]
pub struct BenchQueueArgs {
    #[arg(long)]
    pub json: bool,
    /// The store (default: a throwaway SQLite file; give `postgres://…` to measure PostgreSQL).
    #[arg(long, value_name = "URL")]
    pub store: Option<String>,
    /// Worker (and claimer) counts to compare.
    #[arg(long, value_delimiter = ',', default_values_t = [1usize, 3])]
    pub workers: Vec<usize>,
    /// Real rollouts per worker count (T14, reference agent).
    #[arg(long, default_value_t = 6)]
    pub rollouts: u32,
    /// Synthetic claims per claimer count.
    #[arg(long, default_value_t = 300)]
    pub claims: usize,
}

pub fn run(args: &BenchQueueArgs) -> anyhow::Result<()> {
    if args.workers.is_empty() || args.workers.iter().any(|&n| n == 0 || n > 16) {
        bail!("--workers: counts of 1 to 16");
    }
    if !(1..=100).contains(&args.rollouts) || !(1..=100_000).contains(&args.claims) {
        bail!("--rollouts 1..=100, --claims 1..=100000");
    }
    let tmp = tempfile::tempdir()?;
    let url = args.store.clone().unwrap_or_else(|| libero_store::sqlite_url(&tmp.path().join("queue.sqlite")));
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let store = runtime.block_on(Store::connect(&url))?;
    let tag = libero_records::json::random_name("")?[..8].to_owned();
    let mut claims = Vec::new();
    for &n in &args.workers {
        claims.push(runtime.block_on(claim_latency(&store, &format!("bench_claims_{tag}_{n}"), n, args.claims))?);
    }
    let catalog = libero_tasks::catalog::Catalog::discover()?;
    let (schedule, _) = plan(Experiment::MainTable, catalog.tasks(), Some(&[14]), args.rollouts)?;
    let settings = BatchSettings {
        experiment: "main_table".into(),
        harness: "command".into(),
        harness_version: None,
        model: "reference".into(),
        effort: "high".into(),
        reps: args.rollouts,
        tasks: vec![14],
        pool_tasks: vec![],
        seed: 100,
        wall_time_s: 300.0,
        max_agent_steps: libero_episode::tools::MAX_AGENT_STEPS_CAP,
        agent_cmd: Some("exec {libero_agent} agent --workspace {workspace}".into()),
        sandbox: true,
    };
    let mut rates = Vec::new();
    for &n in &args.workers {
        let name = format!("bench_rollouts_{tag}_{n}");
        runtime.block_on(enqueue(&store, &url, &name, &settings, &schedule, &[]))?;
        let t = Instant::now();
        drain_with_workers(&url, &tmp.path().join(&name), n)?;
        let elapsed_s = t.elapsed().as_secs_f64();
        let b = runtime.block_on(store.batch(&name))?.context("the bench batch left the store")?;
        let doc = BatchDoc::from_value(b.doc).context("the bench batch's document is no object")?;
        if doc.status.as_deref() != Some("finished") {
            bail!("the workers exited before batch {name} finished: {}", json!(doc.counts));
        }
        let outcomes = json!(doc.outcomes);
        if doc.outcomes.as_ref().and_then(|o| o.get(Outcome::Invalid.as_str())).is_some_and(|&n| n > 0) {
            // A measurement of failing rollouts is no measurement: say why they failed (the workers name it).
            let log = std::fs::read_to_string(tmp.path().join(&name).join("worker0.log")).unwrap_or_default();
            let why: Vec<&str> = log.lines().filter(|l| l.contains("INVALID")).take(3).collect();
            eprintln!("{n} worker(s): INVALID rollouts; the first worker says:\n{}", why.join("\n"));
        }
        let per_hour = f64::from(args.rollouts) * 3600.0 / elapsed_s;
        eprintln!("{n} worker(s): {} rollouts in {elapsed_s:.1} s ({per_hour:.0} per hour), outcomes {outcomes}", args.rollouts);
        rates.push(Rate { workers: n, rollouts: args.rollouts, elapsed_s, rollouts_per_hour: per_hour, outcomes, speedup: f64::NAN });
    }
    let first = rates.first().map_or(f64::NAN, |r| r.rollouts_per_hour);
    for r in &mut rates {
        r.speedup = r.rollouts_per_hour / first;
    }
    let out = json!({
        "bench": "queue",
        "backend": format!("{:?}", store.backend()).to_lowercase(),
        "cores": std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
        "claim_latency": claims,
        "rollouts": rates,
    });
    runtime.block_on(store.close());
    if args.json {
        println!("{out}");
    } else {
        println!("{}", serde_json::to_string_pretty(&out)?);
    }
    Ok(())
}

/// `claimers` concurrent claimers drain `claims` synthetic rollouts; each claim call timed.
async fn claim_latency(store: &Store, batch: &str, claimers: usize, claims: usize) -> anyhow::Result<Value> {
    let doc = json!({"schema_version": libero_report::batch::BATCH_SCHEMA, "status": "queued", "rollout_count": claims});
    let jobs: Vec<(String, Value)> = (0..claims).map(|i| (format!("r{i}"), json!({"rollout_id": format!("r{i}")}))).collect();
    store.enqueue(&libero_store::StoredBatch { name: batch.into(), dir: batch.into(), doc, records: vec![] }, &jobs).await?;
    let t = Instant::now();
    let tasks: Vec<_> = (0..claimers)
        .map(|c| {
            let store = store.clone();
            tokio::spawn(async move {
                let mut ms = Vec::new();
                loop {
                    let t = Instant::now();
                    let Some(job) = store.claim(&format!("bench-{c}"), 60_000).await? else { return Ok::<_, anyhow::Error>(ms) };
                    ms.push(t.elapsed().as_secs_f64() * 1000.0);
                    store.finish(&job.batch, &job.rollout_id, &format!("bench-{c}"), &json!({"rollout_id": job.rollout_id, "outcome": "SUCCESS"})).await?;
                }
            })
        })
        .collect();
    let mut ms = Vec::new();
    for t in tasks {
        ms.extend(t.await??);
    }
    let wall_s = t.elapsed().as_secs_f64();
    if ms.len() != claims {
        bail!("{} claims for {claims} queued rollouts", ms.len());
    }
    ms.sort_by(f64::total_cmp);
    let pct = |p: f64| ms[((ms.len() - 1) as f64 * p).round() as usize];
    Ok(json!({"claimers": claimers, "claims": claims, "claim_p50_ms": pct(0.5), "claim_p95_ms": pct(0.95),
              "claims_per_s": claims as f64 / wall_s}))
}

/// Starts `n` workers that exit when the queue is empty, and waits for them.
fn drain_with_workers(url: &str, dir: &Path, n: usize) -> anyhow::Result<()> {
    let exe = std::env::current_exe()?;
    std::fs::create_dir_all(dir)?;
    let mut children = Vec::new();
    for k in 0..n {
        let data = dir.join(format!("worker{k}"));
        let child = Command::new(&exe)
            .args(["worker", "--store", url, "--slots", "1", "--exit-when-idle", "--artifacts"])
            .arg(dir.join("artifacts"))
            .arg("--data")
            .arg(&data)
            .arg("--workspace-root")
            .arg(dir.join(format!("workspaces{k}")))
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join(format!("worker{k}.log")))?)
            .spawn()
            .context("cannot start a worker")?;
        children.push(child);
    }
    let deadline = Instant::now() + Duration::from_secs(3600);
    for mut c in children {
        loop {
            if let Some(st) = c.try_wait()? {
                if !st.success() {
                    let log = std::fs::read_to_string(dir.join("worker0.log")).unwrap_or_default();
                    let tail: Vec<&str> = log.lines().rev().take(20).collect();
                    bail!("a worker failed ({st}); the end of the first worker's log:\n{}", tail.into_iter().rev().collect::<Vec<_>>().join("\n"));
                }
                break;
            }
            if Instant::now() > deadline {
                let _ = c.kill();
                bail!("a worker ran past an hour");
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }
    Ok(())
}

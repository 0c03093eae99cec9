//! `libero-agent tasks list|show`: the release catalog (`tasks/manifest.json`) and the registered pool
//! (`tasks/pool.json`) for operators. `show` prints the
//! private checker parameters too: this is an operator tool, never reachable by an agent.
use anyhow::Context;
use libero_tasks::pool::GROUPS;
use libero_tasks::{Catalog, Member, Pool, PoolEntry, Selection, TaskEntry};

#[derive(Debug, clap::Subcommand)]
pub enum TasksCommand {
    /// The 30 release tasks as a table (or JSON); with `--tasks`, the registered pool (`tasks/pool.json`).
    List {
        #[arg(long)]
        json: bool,
        /// A task selection (docs/commands.md, "Selecting tasks"): `all` for every registered entry with its status,
        /// a suite (`libero_90`, `robomemarena`, …), `stock`, `group:G`, tasks (`T11`, `libero_90/35`), `match:TEXT`;
        /// comma-separated or repeated. Release tasks alone print the release table; anything else the pool's entries
        /// (a release task as its pool twins).
        #[arg(long, value_delimiter = ',')]
        tasks: Vec<String>,
        /// Only tasks of this group (perception, short_horizon, long_horizon) among those selected (default `all`).
        #[arg(long)]
        group: Option<String>,
    },
    /// One task in full: a release task (`T16`, `t16` or `16`) or a pool entry (`libero_90/35`, `suite/name`).
    Show {
        id: String,
        #[arg(long)]
        json: bool,
    },
    /// Regenerate a task's reference image (T22's goal image, protocol §3.9): the task's solving expert plays on a
    /// replica of its episode, then the head camera renders the final state at 256×256. Fails unless every goal
    /// stage holds in the rendered state.
    #[cfg(feature = "episode-serve")]
    GoalImage {
        id: String,
        /// Where to write the PNG (default: the path the manifest names under `assets/`).
        #[arg(long)]
        out: Option<std::path::PathBuf>,
    },
}

pub fn run(cmd: &TasksCommand) -> anyhow::Result<()> {
    let catalog = Catalog::discover().context("loading the task catalog")?;
    match cmd {
        TasksCommand::List { json, tasks, group: None } if tasks.is_empty() => {
            if *json {
                println!("{}", serde_json::to_string_pretty(catalog.tasks())?);
            } else {
                print!("{}", table(catalog.tasks()));
            }
        }
        TasksCommand::List { json, tasks, group } => {
            let pool = Pool::discover().context("loading the task pool")?;
            let selection = if tasks.is_empty() { Selection::all() } else { Selection::from_parts(tasks)? };
            if let Some(g) = group.as_deref().filter(|g| !GROUPS.contains(g)) {
                anyhow::bail!("no group {g:?}; groups: {}", GROUPS.join(", "));
            }
            let picks = selection.resolve(catalog.tasks(), &pool)?;
            let in_group = |g: &str| group.as_deref().is_none_or(|want| want == g);
            if picks.iter().all(|p| matches!(p.member, Member::Release(_))) {
                let chosen: Vec<TaskEntry> = picks
                    .iter()
                    .filter_map(|p| if let Member::Release(t) = p.member { Some(t.clone()) } else { None })
                    .filter(|t| in_group(&t.group))
                    .collect();
                if *json {
                    println!("{}", serde_json::to_string_pretty(&chosen)?);
                } else {
                    print!("{}", table(&chosen));
                }
            } else {
                let mut entries: Vec<&PoolEntry> = Vec::new();
                for p in &picks {
                    let members: Vec<&PoolEntry> = match p.member {
                        Member::Entry(e) => vec![e],
                        Member::Release(t) => pool.entries().iter().filter(|e| e.release_task.as_deref() == Some(&t.id)).collect(),
                    };
                    for e in members.into_iter().filter(|e| in_group(&e.group)) {
                        if !entries.iter().any(|x| std::ptr::eq(*x, e)) {
                            entries.push(e);
                        }
                    }
                }
                print!("{}", pool_list(&pool, &entries, *json)?);
            }
        }
        TasksCommand::Show { id, json } if id.contains('/') => {
            let pool = Pool::discover().context("loading the task pool")?;
            let entry = pool.lookup(id).map_err(anyhow::Error::msg)?;
            if *json {
                println!("{}", serde_json::to_string_pretty(entry)?);
            } else {
                print!("{}", pool_details(entry));
            }
        }
        TasksCommand::Show { id, json } => {
            let task = catalog.get(id).with_context(|| format!("no release task {id:?} (expected T01–T30)"))?;
            if *json {
                println!("{}", serde_json::to_string_pretty(task)?);
            } else {
                print!("{}", details(task)?);
            }
        }
        #[cfg(feature = "episode-serve")]
        TasksCommand::GoalImage { id, out } => goal_image(&catalog, id, out.as_deref())?,
    }
    Ok(())
}

/// Actions the expert may take while producing a goal image (its solve runs ≈ 2,000).
#[cfg(feature = "episode-serve")]
const GOAL_IMAGE_MAX_ACTIONS: u64 = 6_000;

#[cfg(feature = "episode-serve")]
fn goal_image(catalog: &Catalog, id: &str, out: Option<&std::path::Path>) -> anyhow::Result<()> {
    use anyhow::bail;
    use libero_episode::world::{WorldSpec, render_goal_image};
    let task = catalog.get(id).with_context(|| format!("no release task {id:?} (expected T01–T30)"))?;
    let reference = task.task_reference.as_ref().with_context(|| format!("{} has no task_reference", task.id))?;
    let paths = libero_sim::AssetPaths::discover()?;
    let out = out.map_or_else(|| paths.project_assets.join(&reference.path), std::path::Path::to_path_buf);
    // the reference file itself is what is being made: resolve the task without it
    let mut bare = task.clone();
    bare.task_reference = None;
    let files = catalog.files(&bare, &paths)?;
    let (seed, init_index) = (files.placement_seed.map_or(100, u64::from), files.init_index);
    let source = libero_episode::task::suite_task_source(&bare, files);
    let spec = WorldSpec { task: source, level: libero_episode::Level::L1, seed, init_index, paths };
    let renderer = libero_render::Renderer::new().context("cannot open a GPU to render the goal image")?;
    let (image, record) = render_goal_image(&spec, renderer, &task.id, libero_tasks::expert::SOLVE, GOAL_IMAGE_MAX_ACTIONS)?;
    if !record.success || record.completed_required_stage_count != record.required_stage_count {
        bail!(
            "the {} expert did not reach the goal ({} of {} goals: {:?}); not writing {}",
            task.id,
            record.completed_required_stage_count,
            record.required_stage_count,
            record.completed_stage_names,
            out.display()
        );
    }
    if let Some(dir) = out.parent() {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    libero_episode::observation::write_png(&out, image.width, image.height, 3, &image.rgb)
        .with_context(|| format!("writing {}", out.display()))?;
    println!("{}", serde_json::json!({"path": out, "shape": [image.height, image.width, 3], "goals": record.completed_stage_names}));
    Ok(())
}

fn enum_text<T: serde::Serialize>(v: &T) -> String {
    serde_json::to_value(v).ok().and_then(|v| v.as_str().map(str::to_owned)).unwrap_or_default()
}

/// Left-aligned columns, two spaces apart.
fn columns<const N: usize>(header: [&str; N], rows: &[[String; N]]) -> String {
    let mut widths = header.map(str::len);
    for r in rows {
        for (w, c) in widths.iter_mut().zip(r) {
            *w = (*w).max(c.chars().count());
        }
    }
    let line = |cells: Vec<&str>| {
        let padded: Vec<String> = cells.iter().zip(widths).map(|(c, w)| format!("{c:w$}")).collect();
        format!("{}\n", padded.join("  ").trim_end())
    };
    let mut out = line(header.to_vec());
    for r in rows {
        out.push_str(&line(r.iter().map(String::as_str).collect()));
    }
    out
}

fn table(tasks: &[TaskEntry]) -> String {
    let rows: Vec<[String; 8]> = tasks
        .iter()
        .map(|t| {
            [
                t.id.clone(),
                t.name.clone(),
                enum_text(&t.category),
                enum_text(&t.split),
                enum_text(&t.difficulty),
                t.checker.kind.clone(),
                t.stage_count.to_string(),
                if t.implemented { "yes".into() } else { "no".into() },
            ]
        })
        .collect();
    let mut out = columns(["ID", "NAME", "CATEGORY", "SPLIT", "DIFFICULTY", "CHECKER", "K", "IMPLEMENTED"], &rows);
    let implemented = tasks.iter().filter(|t| t.implemented).count();
    out.push_str(&format!(
        "{implemented} of {} tasks implemented; `tasks show <ID>` for details; `tasks list --tasks all` for the pool\n",
        tasks.len()
    ));
    out
}

/// The selected pool entries as a table with the counts of their suites, or as JSON.
fn pool_list(pool: &Pool, entries: &[&PoolEntry], json: bool) -> anyhow::Result<String> {
    if json {
        return Ok(format!("{}\n", serde_json::to_string_pretty(&entries)?));
    }
    let rows: Vec<[String; 7]> = entries
        .iter()
        .map(|e| {
            let status = match (&e.runs_as, e.why_not()) {
                (_, Some(_)) => enum_text(&e.status()).replace('_', " "),
                (Some(t), None) => format!("runs (as {t})"),
                (None, None) => "runs".into(),
            };
            [e.id(), e.name.clone(), e.group.clone(), e.source.clone(), e.checker.clone(), e.stage_count.to_string(), status]
        })
        .collect();
    let mut out = columns(["ID", "NAME", "GROUP", "SOURCE", "CHECKER", "K", "STATUS"], &rows);
    for c in pool.suite_counts().iter().filter(|c| entries.iter().any(|e| e.suite == c.suite)) {
        out.push_str(&format!(
            "{}: {} registered, {} run, {} excluded, {} not implemented\n",
            c.suite, c.registered, c.runs, c.excluded, c.not_implemented
        ));
    }
    let runs = entries.iter().filter(|e| e.why_not().is_none()).count();
    out.push_str(&format!("{runs} of {} listed entries run; `tasks show <suite>/<task id>` for details\n", entries.len()));
    Ok(out)
}

fn pool_details(e: &PoolEntry) -> String {
    let mut out = format!("{} {}\n", e.id(), e.name);
    let mut kv = |k: &str, v: &str| out.push_str(&format!("  {k:<22}{v}\n"));
    kv("instruction", &e.instruction);
    kv("group", &e.group);
    kv("source", &e.source);
    kv("checker", &e.checker);
    kv("K", &e.stage_count.to_string());
    kv("status", &e.why_not().unwrap_or_else(|| "runs".into()));
    for (k, v) in [("runs as", &e.runs_as), ("release task", &e.release_task), ("same definition as", &e.same_definition_as), ("notes", &e.notes)] {
        if let Some(v) = v {
            kv(k, v);
        }
    }
    out
}

fn details(t: &TaskEntry) -> anyhow::Result<String> {
    let mut out = format!("{} {}\n", t.id, t.name);
    let mut kv = |k: &str, v: String| out.push_str(&format!("  {k:<22}{v}\n"));
    kv("category", format!("{} ({}), {}", enum_text(&t.category), t.group, enum_text(&t.difficulty)));
    kv("split", enum_text(&t.split));
    kv("capability", t.capability.clone());
    kv("instruction", t.instruction.clone());
    kv("agent instruction", t.agent_instruction().to_owned());
    kv("source", format!("{} task {}", t.source.suite, t.source.task_id));
    kv("bddl", format!("{} ({})", t.bddl.path, enum_text(&t.bddl.origin)));
    let init_path = t.init.path.clone().unwrap_or_else(|| "-".into());
    kv("init", format!("{} [{}] ({})", init_path, t.init.index, enum_text(&t.init.kind)));
    if let Some(note) = &t.init.note {
        kv("init note", note.clone());
    }
    kv("checker", t.checker.kind.clone());
    kv("K", t.stage_count.to_string());
    kv("implemented", if t.implemented { "yes".into() } else { "no".into() });
    if let Some(why) = &t.not_implemented_reason {
        kv("why not", why.clone());
    }
    if let Some(notes) = &t.notes {
        kv("notes", notes.clone());
    }
    out.push_str("  checker parameters (private):\n");
    for l in serde_json::to_string_pretty(&t.checker.params)?.lines() {
        out.push_str(&format!("    {l}\n"));
    }
    Ok(out)
}

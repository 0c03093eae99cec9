//! Preparing an episode: the task (or a branch's parent), the private run directory and its record, the world on
//! a new episode thread, the workspace with its demonstration, and the entry that keeps the episode.
use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, bail};
use libero_sim::AssetPaths;

use super::log::EpisodeLog;
use super::request::{BranchError, BranchRequest, PrepareRequest, Prepared, valid_episode_id};
use super::{Entry, EpisodeSet, absolute, random_hex};
use crate::demo::record::SourceEpisode;
use crate::demo::{DemoCondition, layout_from_json, project_bundle};
use libero_records::json::{utc_now_iso, write_json_file};
use libero_records::records::{BranchRecord, EPISODE_RECORD_SCHEMA, EpisodeRecord, RecordedTask};
use crate::task::{TaskSource, resolve_task};
use crate::workspace::{DemoNotice, WorkspaceContract, WorkspaceLayout, create_workspace};
use crate::world::{LiberoWorld, WorldSpec};
use crate::{EpisodeConfig, Level, RunDir, spawn_episode_live};

/// A resolved branch: the parent's world and the actions replayed to the branch point.
struct BranchSource {
    request: BranchRequest,
    spec: WorldSpec,
    prefix: Vec<[f64; 7]>,
}

impl EpisodeSet {
    /// Prepares an episode: resolves the task, builds its world on a new episode thread, writes the private
    /// run directory and the workspace, and keeps the episode. A branch's parent is looked for in this
    /// process's run directories.
    pub fn prepare(&self, req: PrepareRequest) -> anyhow::Result<Prepared> {
        self.prepare_with_parent(req, None)
    }

    /// [`Self::prepare`], a branch's parent read from `parent_run` (its run directory as the store knows it)
    /// when given. Errors about the branch are [`BranchError`]s.
    pub fn prepare_with_parent(&self, req: PrepareRequest, parent_run: Option<PathBuf>) -> anyhow::Result<Prepared> {
        let task = req.task.clone();
        let prepared = self.prepare_episode(req, parent_run).inspect_err(|e| tracing::warn!(task, error = format!("{e:#}"), "episode not prepared"));
        // Building a world allocates and frees hundreds of MB in small blocks (the MuJoCo compile of a model the
        // scene may already share, its upload): give them back now, so an open episode costs what it keeps.
        crate::memory::return_freed_memory();
        prepared
    }

    /// Reads the parent's record and action log and checks the branch point (nothing is replayed yet: the branch's
    /// world replays the prefix when it starts, and its live preview at preparation).
    fn branch_source(&self, branch: &BranchRequest, parent_run: Option<PathBuf>, paths: &AssetPaths) -> Result<BranchSource, BranchError> {
        let parent = branch.parent.clone();
        let run = RunDir::new(parent_run.unwrap_or_else(|| self.runs_dir().join(&parent)));
        if !valid_episode_id(&parent) || !run.episode_record().is_file() {
            return Err(BranchError::UnknownParent(parent));
        }
        let not_replayable = |why: String| BranchError::NotReplayable { parent: parent.clone(), why };
        let source = SourceEpisode::read(&run).map_err(|e| not_replayable(e.to_string()))?;
        let mut spec = spec_from_record(&run.episode_record(), paths.clone()).map_err(|e| not_replayable(format!("{e:#}")))?;
        // the parent's own init state (a suite task fixes its row; the record keeps what the episode used)
        spec.init_index = source.init_state_index;
        let available = source.actions.len() as u64;
        if branch.step > available {
            return Err(BranchError::StepOutOfRange { step: branch.step, available });
        }
        let prefix = source.actions.iter().take(branch.step as usize).map(|(_, a)| *a).collect();
        Ok(BranchSource { request: branch.clone(), spec, prefix })
    }

    fn prepare_episode(&self, mut req: PrepareRequest, parent_run: Option<PathBuf>) -> anyhow::Result<Prepared> {
        req.validate()?;
        let level = Level::from_number(req.level).context("level")?;
        let paths = self.paths.clone().context("assets are missing; run `python3 scripts/setup.py`")?;
        let branch = req.branch.as_ref().map(|b| self.branch_source(b, parent_run, &paths)).transpose()?;
        let mut task: TaskSource = match &branch {
            Some(b) => {
                let parent_task = b.spec.task.task_ref.clone();
                if !req.task.trim().is_empty() && req.task != parent_task {
                    return Err(BranchError::OtherTask { parent_task, asked: req.task.clone() }.into());
                }
                req.task = parent_task;
                req.seed = b.spec.seed;
                req.init_index = b.spec.init_index;
                req.layout = b.spec.task.layout;
                b.spec.task.clone()
            }
            None => resolve_task(&req.task, &paths)?,
        };
        task.layout = req.layout;
        let demo_source = match req.demo {
            DemoCondition::None => None,
            _ => Some(self.demo_bundle(&task, req.seed, req.init_index).context("no demonstration for this episode")?),
        };
        let episode_id = format!("ep-{}-{}", compact_utc(), random_hex(4)?);
        let token = random_hex(32)?;
        let run_dir = self.runs_dir().join(&episode_id);
        let workspace = match &req.workspace {
            Some(w) => absolute(w)?,
            None => self.data.join("workspaces").join(&episode_id),
        };
        if is_within(&workspace, &self.runs_dir()) || is_within(&self.runs_dir(), &workspace) {
            bail!("the workspace {} must not overlap the private run directories", workspace.display());
        }
        if WorkspaceLayout::new(&workspace).episode_json().exists() {
            bail!("{} already holds a prepared episode", workspace.display());
        }
        fs::create_dir_all(&run_dir)?;
        let mcp_url = format!("{}/mcp/{episode_id}", self.base_url);
        let mut headers = BTreeMap::new();
        headers.insert("Authorization".to_owned(), format!("Bearer {token}"));
        let record = EpisodeRecord {
            schema_version: Some(EPISODE_RECORD_SCHEMA.to_owned()),
            episode_id: Some(episode_id.clone()),
            created_at: Some(utc_now_iso()),
            task: Some(RecordedTask::from_value(serde_json::to_value(&task)?)?),
            level: Some(u64::from(req.level)),
            seed: Some(req.seed),
            init_state_index: Some(u64::try_from(req.init_index)?),
            max_agent_steps: Some(req.max_agent_steps),
            max_wall_time_seconds: Some(req.wall_time_s),
            demo: Some(req.demo.as_str().to_owned()),
            workspace: Some(workspace.clone()),
            mcp_url: Some(mcp_url.clone()),
            harness: Some(req.harness.clone()),
            model: Some(req.model.clone()),
            batch: Some(req.batch.clone()),
            branch: branch.as_ref().map(|b| BranchRecord {
                parent_episode_id: Some(b.request.parent.clone()),
                parent_control_step: Some(b.request.step),
                replayed_actions: Some(b.prefix.len() as u64),
                prefix_file: Some(crate::branch::PREFIX_FILE.to_owned()),
                counts_toward_max_agent_steps: Some(false),
                rest: serde_json::Map::new(),
            }),
            rest: serde_json::Map::new(),
        };
        let run = RunDir::new(&run_dir);
        write_json_file(&run.episode_record(), &serde_json::to_value(&record)?)?;
        if let Some(b) = &branch {
            crate::branch::write_prefix(&run, &b.prefix).context("cannot keep the branch's replayed actions")?;
            crate::branch::log_branch_point(&run, &b.request.parent, b.request.step).context("cannot start the branch's action log")?;
        }
        let prefix = branch.as_ref().map(|b| b.prefix.clone()).unwrap_or_default();
        let config = EpisodeConfig {
            episode_id: episode_id.clone(),
            instruction: task.instruction.clone(),
            level,
            max_agent_steps: req.max_agent_steps,
            max_wall_time_s: req.wall_time_s,
            workspace: workspace.clone(),
            run_dir: run_dir.clone(),
        };
        let spec = WorldSpec { task: task.clone(), level, seed: req.seed, init_index: req.init_index, paths };
        let renderer = self.renderer()?;
        let video_queue = if req.video { Some(self.video_queue()?) } else { None };
        let (video, state_record) = (run.continuous_video(), run.state_record());
        let telemetry = run.telemetry_jsonl();
        let live = self.live.as_ref().map(|views| views.open(&episode_id, config.agent_step_limit(), config.max_wall_time_s));
        if let (Some(views), Some(b)) = (&self.live, &branch) {
            views.mark_branch(&episode_id, &b.request.parent, b.request.step);
        }
        // The world's events (steps, stages) and the actor's (calls, the end) reach the view through one sink that
        // also tells the owner's event sink what happened (see `actor_sink`).
        let sink = self.actor_sink(&episode_id, live.as_ref().map(|(sink, _)| sink.clone()));
        let world_live = live.map(|(view_sink, viewers)| (sink.clone().unwrap_or(view_sink), viewers));
        // A video that queues behind others draws with models built anew from the same settings (the poses come
        // from the state record), not with the ended world's.
        let rebuild = {
            let (spec, renderer) = (spec.clone(), renderer.clone());
            move || -> Result<crate::video_queue::VideoModels, String> {
                Ok(LiberoWorld::new(&spec, renderer).map_err(|e| e.to_string())?.video_models())
            }
        };
        let make_world = move || {
            let mut world = LiberoWorld::new(&spec, renderer)?;
            world.set_start_prefix(prefix);
            if let Some((sink, viewers)) = world_live {
                world.set_live(sink, viewers, Some(&telemetry))?;
            }
            if let Some(queue) = video_queue {
                world.record_video(&video, &state_record, queue, Some(Box::new(rebuild)))?;
            }
            Ok(world)
        };
        let handle = match spawn_episode_live(config, sink, make_world) {
            Ok(h) => h,
            Err(e) => {
                self.close_live(&episode_id);
                return Err(e).with_context(|| format!("cannot build the simulation for {}", task.task_ref));
            }
        };
        let layout = WorkspaceLayout::new(&workspace);
        let contract = WorkspaceContract {
            instruction: task.instruction.clone(),
            max_agent_steps: req.max_agent_steps,
            max_wall_time_s: req.wall_time_s,
            mcp_url: mcp_url.clone(),
            mcp_headers: headers.clone(),
            demo: req.demo.prompt_notice().map(|notice| DemoNotice { icl_condition: req.demo.icl_condition().into(), notice }),
        };
        let demo = demo_source.as_deref().map(|source| (source, req.demo));
        if let Err(e) = place_workspace(&layout, &contract, demo, &run) {
            // Nobody will ever call this episode: end it now, so its thread and world go.
            handle.stop(&format!("workspace set-up failed: {e:#}"));
            self.close_live(&episode_id);
            return Err(e);
        }
        let log = Arc::new(EpisodeLog::prepared(&episode_id, &req, &task.task_ref, &workspace));
        let entry = Arc::new(Entry { handle, released: false, log });
        self.map
            .write()
            .map_err(|_| anyhow::anyhow!("episode registry lock poisoned"))?
            .insert(episode_id.clone(), entry);
        Ok(Prepared {
            episode_id,
            mcp_url,
            mcp_headers: headers,
            prompt_file: layout.prompt_file(),
            mcp_config_file: layout.mcp_json(),
            workspace,
            run_dir,
            task: task.task_ref,
            instruction: task.instruction,
            level: req.level,
            branch: branch.map(|b| b.request),
        })
    }
}

fn is_within(child: &Path, parent: &Path) -> bool {
    child.starts_with(parent)
}

/// The world an episode ran on, from its private record (`task.task_ref`, `level`, `seed`, `init_state_index`).
pub(super) fn spec_from_record(record: &Path, paths: AssetPaths) -> anyhow::Result<WorldSpec> {
    let text = fs::read(record).with_context(|| format!("cannot read {}", record.display()))?;
    let v: EpisodeRecord = serde_json::from_slice(&text)?;
    let task_ref = v.task_ref().context("the episode record names no task")?;
    let level = v.level.and_then(|l| Level::from_number(u8::try_from(l).ok()?)).context("the episode record has no level")?;
    let seed = v.seed.context("the episode record has no seed")?;
    let init_index = v.init_state_index.context("the episode record has no init state index")?;
    let mut task = resolve_task(task_ref, &paths)?;
    task.layout = layout_from_json(v.layout())?;
    Ok(WorldSpec { task, level, seed, init_index: usize::try_from(init_index)?, paths })
}

/// The agent's workspace (prompt, MCP config, the demonstration if any) and the prompt's private copy.
fn place_workspace(
    layout: &WorkspaceLayout,
    contract: &WorkspaceContract,
    demo: Option<(&Path, DemoCondition)>,
    run: &RunDir,
) -> anyhow::Result<()> {
    create_workspace(layout, contract).with_context(|| format!("cannot create the workspace {}", layout.root.display()))?;
    if let Some((source, condition)) = demo {
        let receipt = project_bundle(source, &layout.expert_demo(), condition, &contract.instruction)
            .context("cannot place the demonstration in the workspace")?;
        write_json_file(&run.root.join("icl_projection_receipt.json"), &serde_json::to_value(&receipt)?)?;
    }
    fs::copy(layout.prompt_file(), run.agent_prompt()).context("cannot keep a private copy of the prompt")?;
    Ok(())
}

/// `YYYYMMDDTHHMMSSZ` for episode ids (sortable by creation time).
fn compact_utc() -> String {
    let iso = utc_now_iso(); // 2026-11-21T17:03:04.123456+00:00
    let digits: String = iso[..19].chars().filter(|c| c.is_ascii_digit() || *c == 'T').collect();
    format!("{digits}Z")
}

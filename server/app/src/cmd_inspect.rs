//! `libero-agent sim inspect`: compose a BDDL scene, place its fixtures for a seed as LIBERO's reset does,
//! optionally load an init state, and print the compiled model as JSON (bodies, joints, geoms, cameras, sites,
//! masses, plus the composer's object/fixture/region tables).
use std::path::PathBuf;

use anyhow::Context;
use libero_sim::compose::compose_file;
use libero_sim::scene_setup::PreparedScene;
use libero_sim::mujoco_rs::prelude::*;
use libero_sim::placement::update_visual_sites;
use libero_sim::AssetPaths;
use serde_json::{Value, json};

/// Arguments of `sim inspect`.
#[derive(Debug, Clone, clap::Args)]
pub struct InspectArgs {
    /// BDDL problem file (stock LIBERO or authored).
    #[arg(long)]
    pub bddl: PathBuf,
    /// LIBERO init-state file (`.pruned_init` / `.init`) whose row `--init-index` is loaded before dumping.
    #[arg(long)]
    pub init_file: Option<PathBuf>,
    /// Row of the init file.
    #[arg(long, default_value_t = 0)]
    pub init_index: usize,
    /// `env.seed(seed)` before the reset that places the fixtures.
    #[arg(long, default_value_t = 0)]
    pub seed: u32,
    /// Print the merged MJCF instead of the JSON dump.
    #[arg(long)]
    pub mjcf: bool,
}

fn name(m: &MjModel, ty: MjtObjBase, id: usize) -> Value {
    m.id_to_name(ty, id).map(|s| Value::String(s.to_string())).unwrap_or(Value::Null)
}

/// Compose, place and dump; returns the JSON document.
pub fn inspect(args: &InspectArgs) -> anyhow::Result<Value> {
    let paths = AssetPaths::discover()?;
    let init = args.init_file.as_deref().map(|f| (f, args.init_index));
    let prepared = PreparedScene::prepare(&args.bddl, &paths, args.seed, init)
        .with_context(|| format!("setting up {}", args.bddl.display()))?;
    let nq = prepared.model.ffi().nq as usize;
    let nv = prepared.model.ffi().nv as usize;
    let row = prepared.start_row.clone();
    let (scene, mut model, placement) = (prepared.scene, prepared.model, prepared.placement);
    let mut init_state = Value::Null;
    if let Some(file) = &args.init_file {
        // LIBERO's stove-burner toggle after set_init_state
        update_visual_sites(&scene, &mut model, &row[1..1 + nq])?;
        init_state = json!({"file": file, "index": args.init_index, "time": row[0]});
    }
    // The init row, or the state LIBERO has right after reset(): robot at init_qpos, objects and articulations
    // as sampled.
    let mut data = MjData::new(&model);
    data.qpos_mut().copy_from_slice(&row[1..1 + nq]);
    data.qvel_mut().copy_from_slice(&row[1 + nq..1 + nq + nv]);
    // SAFETY: plain scalar write into the data this function owns.
    unsafe { data.ffi_mut().time = row[0] };
    data.forward();
    let m = &model;
    let bodies: Vec<Value> = (0..m.ffi().nbody as usize)
        .map(|i| {
            json!({"id": i, "name": name(m, MjtObjBase::mjOBJ_BODY, i), "parent": m.body_parentid()[i],
                   "pos": m.body_pos()[i], "quat_wxyz": m.body_quat()[i], "mass_kg": m.body_mass()[i],
                   "inertia": m.body_inertia()[i], "xpos": data.xpos()[i], "xquat_wxyz": data.xquat()[i]})
        })
        .collect();
    let jtype = |t: MjtJoint| match t {
        MjtJoint::mjJNT_FREE => "free",
        MjtJoint::mjJNT_BALL => "ball",
        MjtJoint::mjJNT_SLIDE => "slide",
        _ => "hinge",
    };
    let joints: Vec<Value> = (0..m.ffi().njnt as usize)
        .map(|j| {
            let dof = m.jnt_dofadr()[j] as usize;
            json!({"id": j, "name": name(m, MjtObjBase::mjOBJ_JOINT, j), "type": jtype(m.jnt_type()[j]),
                   "body": m.jnt_bodyid()[j], "qposadr": m.jnt_qposadr()[j], "dofadr": dof,
                   "limited": m.jnt_limited()[j], "range": m.jnt_range()[j], "damping": m.dof_damping()[dof],
                   "armature": m.dof_armature()[dof], "frictionloss": m.dof_frictionloss()[dof]})
        })
        .collect();
    let geoms: Vec<Value> = (0..m.ffi().ngeom as usize)
        .map(|g| {
            json!({"id": g, "name": name(m, MjtObjBase::mjOBJ_GEOM, g), "body": m.geom_bodyid()[g],
                   "type": m.geom_type()[g] as i32, "group": m.geom_group()[g], "size": m.geom_size()[g],
                   "contype": m.geom_contype()[g], "conaffinity": m.geom_conaffinity()[g], "friction": m.geom_friction()[g]})
        })
        .collect();
    let cameras: Vec<Value> = (0..m.ffi().ncam as usize)
        .map(|c| {
            json!({"id": c, "name": name(m, MjtObjBase::mjOBJ_CAMERA, c), "body": m.cam_bodyid()[c],
                   "fovy_deg": m.cam_fovy()[c], "pos": m.cam_pos()[c], "quat_wxyz": m.cam_quat()[c],
                   "xpos": data.cam_xpos()[c], "xmat": data.cam_xmat()[c]})
        })
        .collect();
    let sites: Vec<Value> = (0..m.ffi().nsite as usize)
        .map(|s| {
            json!({"id": s, "name": name(m, MjtObjBase::mjOBJ_SITE, s), "body": m.site_bodyid()[s],
                   "pos": m.site_pos()[s], "size": m.site_size()[s], "rgba": m.site_rgba()[s], "xpos": data.site_xpos()[s]})
        })
        .collect();
    let total_mass: f64 = m.body_mass().iter().sum();
    Ok(json!({
        "bddl": args.bddl, "problem": scene.problem_name, "problem_class": scene.problem_class,
        "language": scene.language, "seed": args.seed, "init_state": init_state,
        "counts": {"nq": nq, "nv": nv, "nu": m.ffi().nu, "nbody": m.ffi().nbody, "njnt": m.ffi().njnt,
                   "ngeom": m.ffi().ngeom, "nsite": m.ffi().nsite, "ncam": m.ffi().ncam},
        "timestep_s": m.opt().timestep, "total_mass_kg": total_mass,
        "robot_base_pos": scene.robot_base_pos, "objects": scene.objects, "fixtures": scene.fixtures,
        "regions": scene.regions, "placement": placement,
        "bodies": bodies, "joints": joints, "geoms": geoms, "cameras": cameras, "sites": sites,
    }))
}

/// Entry point for `sim inspect`: prints JSON (or the MJCF with `--mjcf`) on stdout.
pub fn run(args: &InspectArgs) -> anyhow::Result<()> {
    if args.mjcf {
        let paths = AssetPaths::discover()?;
        let scene = compose_file(&args.bddl, &paths)?;
        println!("{}", scene.mjcf);
        return Ok(());
    }
    let doc = inspect(args)?;
    println!("{}", serde_json::to_string_pretty(&doc)?);
    Ok(())
}

//! BDDL problem → the MJCF robosuite 1.4.0 + LIBERO hand to MuJoCo → `MjModel`.
//!
//! The composer replays robosuite's XML edits in robosuite's order (see `libero_port_notes.md` §5.2), so that the
//! merged document is element-for-element the one LIBERO builds (`golden/*.mjcf_input.xml`), numbers included
//! (Python float formatting is reproduced). Compilation goes through MuJoCo's model-editing API (`MjSpec`).
//! Fixture placement and other post-compile model edits live in [`crate::placement`].
use std::path::{Path, PathBuf};

use libero_bddl::Problem;
use mujoco_rs::prelude::{MjModel, MjSpec};

use crate::{AssetPaths, SimError};

pub mod mjxml;
pub mod registry;
pub mod xml;

use mjxml::{add_prefix, prepare_model, recolor_collision_geoms, set_joint_attribute, MjXml};
use xml::{array_to_string, py_float, string_to_array, Element};

/// The LIBERO problem classes (`TASK_MAPPING`), selected by the BDDL `(problem NAME)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum ProblemClass {
    Tabletop,
    Kitchen,
    LivingRoom,
    Study,
    Floor,
    CoffeeTable,
    /// Libero-Agent's `Libero_Robosuite_Door_Manipulation` (T28): robosuite 1.4's own Door scene — the stock
    /// `TableArena` (0.8 × 0.3 × 0.05 table at offset (−0.2, −0.35, 0.8)), the Panda on its default Rethink mount,
    /// robosuite's agentview, fixtures placed with z_offset 0 (task catalog §2.3).
    RobosuiteDoor,
}

/// A camera the problem class sets on the arena (`_setup_camera`), world frame, quaternion (w, x, y, z).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct CameraSpec {
    pub name: &'static str,
    pub pos: [f64; 3],
    pub quat: [f64; 4],
}

const AGENT_TABLE_QUAT: [f64; 4] = [0.6380177736282349, 0.3048497438430786, 0.30484986305236816, 0.6380177736282349];
const AGENT_LOW_QUAT: [f64; 4] = [0.6182166934013367, 0.3432307541370392, 0.3432314395904541, 0.6182177066802979];
const SIDE_QUAT: [f64; 4] = [0.56, 0.43, 0.43, 0.56];
const GALLERY: CameraSpec = CameraSpec {
    name: "galleryview",
    pos: [2.844547668904445, 2.1279684793440667, 3.128616846013882],
    quat: [0.42261379957199097, 0.23374411463737488, 0.41646939516067505, 0.7702690958976746],
};
const PAPER_QUAT: [f64; 4] = [0.513, 0.353, 0.443, 0.645];
/// robosuite Door's agentview position (`Door._load_model`), kept by the door problem class.
const DOOR_AGENT_POS: [f64; 3] = [0.5986131746834771, -4.392035683362857e-09, 1.5903500240372423];

impl ProblemClass {
    /// `TASK_MAPPING[name.lower()]`.
    pub fn from_problem_name(name: &str) -> Option<Self> {
        Some(match name.to_ascii_lowercase().as_str() {
            "libero_tabletop_manipulation" => Self::Tabletop,
            "libero_kitchen_tabletop_manipulation" => Self::Kitchen,
            "libero_living_room_tabletop_manipulation" => Self::LivingRoom,
            "libero_study_tabletop_manipulation" => Self::Study,
            "libero_floor_manipulation" => Self::Floor,
            "libero_coffee_table_manipulation" => Self::CoffeeTable,
            "libero_robosuite_door_manipulation" => Self::RobosuiteDoor,
            _ => return None,
        })
    }

    /// The workspace fixture name used as region target (`main_table`, `kitchen_table`, ...).
    pub fn workspace_name(self) -> &'static str {
        match self {
            Self::Tabletop | Self::RobosuiteDoor => "main_table",
            Self::Kitchen => "kitchen_table",
            Self::LivingRoom => "living_room_table",
            Self::Study => "study_table",
            Self::Floor => "floor",
            Self::CoffeeTable => "coffee_table",
        }
    }

    /// The fixture category that stands for the workspace itself and is not loaded.
    pub fn workspace_category(self) -> &'static str {
        match self {
            Self::Tabletop | Self::RobosuiteDoor => "table",
            other => other.workspace_name(),
        }
    }

    /// Key into `REGION_SAMPLERS[problem]` (the workspace category).
    pub fn uses_libero100_sampler(self) -> bool {
        matches!(self, Self::LivingRoom | Self::Study | Self::Kitchen)
    }

    /// The arena file: LIBERO's scene styles, or robosuite's own `arenas/table_arena.xml` for the door scene.
    fn scene_xml(self) -> &'static str {
        match self {
            Self::RobosuiteDoor => "arenas/table_arena.xml",
            Self::Tabletop => "scenes/libero_tabletop_base_style.xml",
            Self::Kitchen => "scenes/libero_kitchen_tabletop_base_style.xml",
            Self::LivingRoom => "scenes/libero_living_room_tabletop_base_style.xml",
            Self::Study => "scenes/libero_study_base_style.xml",
            Self::Floor => "scenes/libero_floor_base_style.xml",
            Self::CoffeeTable => "scenes/libero_coffee_table_base_style.xml",
        }
    }

    /// (floor texture, wall texture) of the default style (`arenas/style.py`); `None` for robosuite's own arena,
    /// which keeps the textures its file names.
    fn textures(self) -> Option<(&'static str, &'static str)> {
        Some(match self {
            Self::Tabletop | Self::Study | Self::Floor => ("light-gray-floor-tile.png", "light-gray-plaster.png"),
            Self::Kitchen => ("gray_ceramic_tile.png", "yellow_linen_wall_texture.png"),
            Self::LivingRoom | Self::CoffeeTable => ("seamless_wood_planks_floor.png", "light-gray-plaster.png"),
            Self::RobosuiteDoor => return None,
        })
    }

    /// Full table size (x, y, z) in metres; `None` for the floor.
    pub fn table_full_size(self) -> Option<[f64; 3]> {
        match self {
            Self::Tabletop | Self::Kitchen | Self::Study => Some([1.0, 1.2, 0.05]),
            Self::LivingRoom | Self::CoffeeTable => Some([0.70, 1.6, 0.024]),
            Self::RobosuiteDoor => Some([0.8, 0.3, 0.05]),
            Self::Floor => None,
        }
    }

    /// `workspace_offset` = the reference position of the placement samplers (metres, world frame).
    pub fn workspace_offset(self) -> [f64; 3] {
        match self {
            Self::Tabletop | Self::Kitchen => [0.0, 0.0, 0.90],
            Self::LivingRoom | Self::CoffeeTable => [0.0, 0.0, 0.41],
            Self::Study => [-0.2, 0.0, 0.867],
            Self::Floor => [0.0, 0.0, -0.035],
            Self::RobosuiteDoor => [-0.2, -0.35, 0.8],
        }
    }

    /// z offset of fixture placement (`0.01 - table_full_size[2]`, floor −0.025; 0 for the door scene, whose
    /// door asset's `bottom_site` is calibrated for robosuite's own sampler).
    pub fn fixture_z_offset(self) -> f64 {
        if self == Self::RobosuiteDoor {
            return 0.0;
        }
        match self.table_full_size() {
            Some(s) => 0.01 - s[2],
            None => -0.025,
        }
    }

    /// MountedPanda (RethinkMount) or OnTheGroundPanda (NullMount).
    pub fn robot_is_mounted(self) -> bool {
        matches!(self, Self::Tabletop | Self::Kitchen | Self::Study | Self::RobosuiteDoor)
    }

    /// `robot_model.base_xpos_offset[key](table_length)`: where the robot base's bottom goes.
    fn robot_base_xpos(self) -> [f64; 3] {
        let l = self.table_full_size().map(|s| s[0]).unwrap_or(0.0);
        match self {
            // robosuite Panda `base_xpos_offset["table"]`: the same rule on the door scene's 0.8 m table
            Self::Tabletop | Self::Kitchen | Self::RobosuiteDoor => [-0.16 - l / 2.0, 0.0, 0.0],
            Self::Study => [-0.25 - l / 2.0, 0.0, 0.0],
            Self::LivingRoom => [-0.16 - l / 2.0, 0.0, 0.42],
            Self::CoffeeTable => [-0.16 - l / 2.0, 0.0, 0.41],
            Self::Floor => [-0.6, 0.0, 0.0],
        }
    }

    /// Body that carries the table-region sites.
    fn region_body(self) -> &'static str {
        match self {
            Self::Tabletop | Self::Kitchen | Self::RobosuiteDoor => "table",
            Self::Study => "study_table",
            Self::LivingRoom => "living_room_table",
            Self::Floor => "floor",
            Self::CoffeeTable => "coffee_table",
        }
    }

    /// Cameras in the order `_setup_camera` sets them.
    pub fn cameras(self) -> Vec<CameraSpec> {
        let agent = |pos, quat| CameraSpec { name: "agentview", pos, quat };
        let front = |pos| CameraSpec { name: "frontview", pos, quat: SIDE_QUAT };
        let paper = |pos| CameraSpec { name: "paperview", pos, quat: PAPER_QUAT };
        match self {
            Self::Tabletop => vec![
                agent([0.6586131746834771, 0.0, 1.6103500240372423], AGENT_TABLE_QUAT),
                front([1.0, 0.0, 1.48]),
                GALLERY,
            ],
            Self::Kitchen => vec![
                agent([0.6586131746834771, 0.0, 1.6103500240372423], AGENT_TABLE_QUAT),
                front([1.0, 0.0, 1.48]),
                GALLERY,
                paper([2.1, 0.535, 2.075]),
            ],
            Self::Study => vec![
                agent([0.4586131746834771, 0.0, 1.6103500240372423], AGENT_TABLE_QUAT),
                front([1.0, 0.0, 1.48]),
                GALLERY,
                paper([2.1, 0.535, 2.075]),
            ],
            Self::LivingRoom => vec![
                agent([0.6065773716836134, 0.0, 0.96], AGENT_LOW_QUAT),
                front([1.5, 0.0, 0.9]),
                GALLERY,
                paper([2.1, 0.735, 1.875]),
            ],
            Self::Floor => vec![
                agent([0.8965773716836134, 5.216182733499864e-07, 0.65], AGENT_LOW_QUAT),
                front([1.0, 0.0, 0.65]),
                GALLERY,
            ],
            Self::CoffeeTable => vec![
                agent([1.5, 0.0, 0.9], SIDE_QUAT),
                GALLERY,
                CameraSpec {
                    name: "canonical_agentview",
                    pos: [0.5386131746834771, 0.0, 0.7903500240372423],
                    quat: AGENT_TABLE_QUAT,
                },
            ],
            // the arena file's own frontview / birdview / sideview stay as robosuite writes them
            Self::RobosuiteDoor => vec![
                agent(DOOR_AGENT_POS, AGENT_TABLE_QUAT),
                CameraSpec { name: "canonical_agentview", pos: DOOR_AGENT_POS, quat: AGENT_TABLE_QUAT },
            ],
        }
    }
}

/// A movable object or fixture instance in the composed model.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct InstanceInfo {
    pub name: String,
    pub category: String,
    pub is_fixture: bool,
    /// `<name>_main`.
    pub root_body: String,
    /// Prefixed joint names of the instance in document order (free joint last for objects).
    pub joints: Vec<String>,
    /// Placement offsets from the asset's `bottom_site`/`top_site`/`horizontal_radius_site` (metres).
    pub bottom_offset: [f64; 3],
    pub top_offset: [f64; 3],
    pub horizontal_radius: f64,
    pub rotation: registry::Rotation,
    pub articulation: Option<registry::Articulation>,
    /// Prefixed names of the visual-state sites (flat_stove burner).
    pub vis_sites: Vec<String>,
    /// Prefixed names of every site in the instance (robosuite `model.sites`, order of `sort_elements`).
    pub sites: Vec<String>,
}

/// A BDDL region as it exists in the model.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RegionInfo {
    /// BDDL key `<target>_<name>`; also the MuJoCo site name.
    pub key: String,
    pub target: String,
    /// Instance that owns the site, or `None` for workspace (table-zone) regions.
    pub parent: Option<String>,
    /// Joints of the innermost body holding the site (drawer slides), LIBERO `SiteObject.joints`.
    pub joints: Vec<String>,
    /// Half size as written in the XML / TargetZone (metres).
    pub size: Vec<f64>,
    pub ranges: Vec<[f64; 4]>,
    pub yaw_rotation: [f64; 2],
}

/// The merged scene: MJCF text plus what downstream code needs to know about it.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ComposedScene {
    pub bddl_file: Option<PathBuf>,
    pub problem_name: String,
    pub problem_class: ProblemClass,
    pub language: String,
    /// The MJCF handed to MuJoCo (absolute asset paths).
    #[serde(skip)]
    pub mjcf: String,
    /// World position of `robot0_base` as set by `set_base_xpos` (metres).
    pub robot_base_pos: [f64; 3],
    pub robot_mounted: bool,
    pub objects: Vec<InstanceInfo>,
    pub fixtures: Vec<InstanceInfo>,
    pub regions: Vec<RegionInfo>,
    pub workspace_offset: [f64; 3],
    pub fixture_z_offset: f64,
    /// Robot sites (`robot0_*`, `gripper0_*`, `mount0_*`) that `visualize(False)` hides at reset.
    pub robot_sites: Vec<String>,
    #[serde(skip)]
    pub problem: Problem,
}

impl ComposedScene {
    /// [`Self::compile`], once per scene while an episode of it is alive: returns a private copy to edit and the
    /// compiled scene it was copied from, which the caller holds for as long as it uses the copy (see
    /// [`crate::shared_model::compiled`]).
    pub fn compile_shared(&self) -> Result<(MjModel, std::sync::Arc<MjModel>), SimError> {
        crate::shared_model::compiled(&self.mjcf, || self.compile())
    }

    /// Compile through MuJoCo's model-editing API.
    pub fn compile(&self) -> Result<MjModel, SimError> {
        if self.mjcf.contains('\0') {
            return Err(SimError::Input("MJCF contains a NUL byte".into()));
        }
        let mut spec = MjSpec::from_xml_string(&self.mjcf).map_err(|e| SimError::Compile(format!("parse: {e}")))?;
        spec.compile().map_err(|e| SimError::Compile(e.to_string()))
    }

    pub fn instance(&self, name: &str) -> Option<&InstanceInfo> {
        self.objects.iter().chain(&self.fixtures).find(|i| i.name == name)
    }
}

/// Parse `bddl` and compose it with the cached assets.
pub fn compose_file(bddl: &Path, paths: &AssetPaths) -> Result<ComposedScene, SimError> {
    let problem = Problem::from_file(bddl).map_err(|e| SimError::Input(e.to_string()))?;
    let mut scene = compose(&problem, paths)?;
    scene.bddl_file = Some(bddl.to_path_buf());
    Ok(scene)
}

/// A loaded LIBERO object (`MujocoXMLObject`) ready to merge.
struct LoadedObject {
    info: InstanceInfo,
    body: Element,
    assets: Element,
    /// `<sensor>` entries of a project asset (prefixed), e.g. the button's touch sensor. robosuite merges only an
    /// object's body and assets; LIBERO's own objects carry no sensors, so this is empty for them.
    sensors: Element,
    /// Region sites of this instance: (site name without prefix, size, joints of the innermost body).
    site_scan: Vec<(String, Vec<f64>, Vec<String>)>,
}

fn vec3(v: &[f64]) -> [f64; 3] {
    [v.first().copied().unwrap_or(0.0), v.get(1).copied().unwrap_or(0.0), v.get(2).copied().unwrap_or(0.0)]
}

/// Applies a derived category's declared edits (registry [`registry::AssetEdit`]) to the asset's outer body.
fn apply_edits(outer: &mut Element, edits: &[registry::AssetEdit], file: &Path) -> Result<(), SimError> {
    let missing = |tag: &str, name: &str| SimError::Assets(format!("{}: edit names no <{tag} name=\"{name}\">", file.display()));
    for edit in edits {
        match edit {
            registry::AssetEdit::Set { tag, name, attr, from, to } => {
                let e = outer.find_named_mut(tag, name).ok_or_else(|| missing(tag, name))?;
                let now = e.get(attr).unwrap_or("");
                if now != *from {
                    return Err(SimError::Assets(format!(
                        "{}: <{tag} name=\"{name}\"> {attr}=\"{now}\", the edit expects \"{from}\" (asset changed?)",
                        file.display()
                    )));
                }
                e.set(attr, *to);
            }
            registry::AssetEdit::Add { body, tag, attrs } => {
                let owned: Vec<(&str, String)> = attrs.iter().map(|(k, v)| (*k, (*v).to_owned())).collect();
                outer.find_named_mut("body", body).ok_or_else(|| missing("body", body))?.children.push(Element::with_attrs(tag, &owned));
            }
        }
    }
    Ok(())
}

/// `MujocoXMLObject(fname, name, joints, obj_type="all", duplicate_collision_geoms=False)`.
fn load_object(name: &str, cat: &registry::Category, is_fixture: bool, paths: &AssetPaths) -> Result<LoadedObject, SimError> {
    let file = match cat.root {
        registry::AssetRoot::Libero => paths.libero_assets.join(&cat.file),
        registry::AssetRoot::Project => paths.project_assets.join(&cat.file),
    };
    let mut xml = MjXml::load(&file)?;
    let prefix = format!("{name}_");
    let mut outer = xml
        .section("worldbody")
        .children
        .iter()
        .find(|c| c.tag == "body")
        .ok_or_else(|| SimError::Assets(format!("{}: no outer body", file.display())))?
        .clone();
    let no_object = || SimError::Assets(format!("{}: no body named `object` in the outer body", file.display()));
    // geoms in document order: keep groups 0/1, name unnamed ones g{i}
    fn filter_geoms(e: &mut Element, counter: &mut usize, file: &Path) -> Result<(), SimError> {
        let mut kept = Vec::with_capacity(e.children.len());
        for mut c in std::mem::take(&mut e.children) {
            if c.tag == "geom" {
                let i = *counter;
                *counter += 1;
                let group: i64 = c
                    .get("group")
                    .and_then(|g| g.trim().parse().ok())
                    .ok_or_else(|| SimError::Assets(format!("{}: geom without an integer group", file.display())))?;
                if group != 0 && group != 1 {
                    continue;
                }
                if c.get("name").is_none() {
                    c.set("name", format!("g{i}"));
                }
                kept.push(c);
            } else {
                filter_geoms(&mut c, counter, file)?;
                kept.push(c);
            }
        }
        e.children = kept;
        Ok(())
    }
    let mut counter = 0;
    filter_geoms(outer.child_named_mut("body", "object").ok_or_else(no_object)?, &mut counter, &file)?;
    apply_edits(&mut outer, cat.edits, &file)?;
    let mut obj = outer.child_named("body", "object").ok_or_else(no_object)?.clone();
    obj.set("name", "main");
    if !is_fixture && cat.free_joint_as_object {
        obj.children.push(Element::with_attrs(
            "joint",
            &[("type", "free".into()), ("damping", "0.0005".into()), ("name", "joint0".into())],
        ));
    }
    obj.children.push(Element::with_attrs(
        "site",
        &[
            ("pos", "0 0 0".into()),
            ("size", "0.002 0.002 0.002".into()),
            ("rgba", "1 0 0 0".into()),
            ("type", "sphere".into()),
            ("group", "0".into()),
            ("name", "default_site".into()),
        ],
    ));
    // region-site scan of `_load_sites_in_arena` on the unprefixed asset tree: for every body below the outer
    // body's first child (pre-order), its sites (recursive) with the joints that are its direct children; the scan
    // stops at the first body without sites.
    let mut site_scan = Vec::new();
    {
        let mut bodies: Vec<&Element> = Vec::new();
        fn bodies_below<'a>(e: &'a Element, out: &mut Vec<&'a Element>) {
            for c in &e.children {
                if c.tag == "body" {
                    out.push(c);
                }
                bodies_below(c, out);
            }
        }
        bodies_below(&outer, &mut bodies);
        for part in bodies {
            let mut sites: Vec<&Element> = Vec::new();
            part.walk(None, &mut |e, _| {
                if e.tag == "site" {
                    sites.push(e);
                }
            });
            if sites.is_empty() {
                break;
            }
            let joints: Vec<String> = part
                .children
                .iter()
                .filter(|c| c.tag == "joint")
                .filter_map(|c| c.get("name").map(|n| format!("{prefix}{n}")))
                .collect();
            for s in sites {
                let size = s.get("size").map(string_to_array).transpose()?.unwrap_or_default();
                site_scan.push((s.get("name").unwrap_or("").to_string(), size, joints.clone()));
            }
        }
    }
    add_prefix(&mut obj, &prefix);
    add_prefix(&mut xml.root, &prefix);
    let site_pos = |site: &str| -> Result<Vec<f64>, SimError> {
        let s = outer
            .child_named("site", site)
            .ok_or_else(|| SimError::Assets(format!("{}: missing site `{site}`", file.display())))?;
        string_to_array(s.get("pos").unwrap_or("0 0 0"))
    };
    let bottom = vec3(&site_pos("bottom_site")?);
    let top = vec3(&site_pos("top_site")?);
    let radius = site_pos("horizontal_radius_site")?.first().copied().unwrap_or(0.0);
    let mut joints = Vec::new();
    let mut sites = Vec::new();
    obj.walk(None, &mut |e, parent| {
        if e.tag == "joint" && parent.is_none_or(|p| p.tag != "actuator") && e.get("joint").is_none() && e.get("joint1").is_none() {
            joints.push(e.get("name").unwrap_or("").to_string());
        }
        if e.tag == "site" {
            sites.push(e.get("name").unwrap_or("").to_string());
        }
    });
    if let Some(exposed) = cat.exposed_joints {
        joints.retain(|j| exposed.iter().any(|e| j.strip_prefix(&prefix) == Some(*e)));
    }
    let vis_sites = cat.vis_sites.iter().map(|s| format!("{prefix}{s}")).collect();
    Ok(LoadedObject {
        info: InstanceInfo {
            name: name.to_string(),
            category: cat.key.to_string(),
            is_fixture,
            root_body: format!("{prefix}main"),
            joints,
            bottom_offset: bottom,
            top_offset: top,
            horizontal_radius: radius,
            rotation: cat.rotation.clone(),
            articulation: cat.articulation.clone(),
            vis_sites,
            sites,
        },
        body: obj,
        assets: xml.section("asset").clone(),
        sensors: match cat.root {
            registry::AssetRoot::Project => xml.section("sensor").clone(),
            registry::AssetRoot::Libero => Element::new("sensor"),
        },
        site_scan,
    })
}

/// Robot (arm + mount + gripper) as robosuite's `SingleArm.load_model` + `set_base_xpos` build it.
fn build_robot(class: ProblemClass, paths: &AssetPaths) -> Result<(MjXml, [f64; 3], Vec<String>), SimError> {
    let rs = &paths.robosuite_assets;
    let mut robot = MjXml::load(&rs.join("robots/panda/robot.xml"))?;
    let robot_info = prepare_model(&mut robot, "robot0_", &mjxml::ROBOT_COLLISION_COLOR)?;
    // RobotModel.__init__ defaults (only where absent), then Panda's forced damping
    set_joint_attribute(&mut robot.root, "frictionloss", &[0.1; 7], false)?;
    set_joint_attribute(&mut robot.root, "damping", &[0.1; 7], false)?;
    let armature: Vec<f64> = (0..7).map(|i| 5.0 / (i as f64 + 1.0)).collect();
    set_joint_attribute(&mut robot.root, "armature", &armature, false)?;
    set_joint_attribute(&mut robot.root, "damping", &[0.1, 0.1, 0.1, 0.1, 0.1, 0.01, 0.01], true)?;
    // mount
    let (mount_file, mount_top) = if class.robot_is_mounted() {
        ("mounts/rethink_mount.xml", [0.0, 0.0, -0.01])
    } else {
        ("mounts/null_mount.xml", [0.0, 0.0, 0.0])
    };
    let mut mount = MjXml::load(&rs.join(mount_file))?;
    let mount_info = prepare_model(&mut mount, "mount0_", &mjxml::MOUNT_COLLISION_COLOR)?;
    let offset: Vec<f64> = (0..3).map(|k| robot_info.base_offset[k] - mount_top[k]).collect();
    mount
        .section_mut("worldbody")
        .find_named_mut("body", &mount_info.root_body)
        .ok_or_else(|| SimError::Assets("mount root body vanished".into()))?
        .set("pos", array_to_string(&offset));
    robot.merge(mount, Some(&robot_info.root_body))?;
    // gripper
    let mut gripper = MjXml::load(&rs.join("grippers/panda_gripper.xml"))?;
    prepare_model(&mut gripper, "gripper0_", &mjxml::GRIPPER_COLLISION_COLOR)?;
    robot.merge(gripper, Some("robot0_right_hand"))?;
    // set_base_xpos(pos): root pos = pos - ((mount.bottom_offset - mount.top_offset) + robot.base_offset)
    let xpos = class.robot_base_xpos();
    let mut base = [0.0; 3];
    for k in 0..3 {
        let bottom = (mount_info.base_offset[k] - mount_top[k]) + robot_info.base_offset[k];
        base[k] = xpos[k] - bottom;
    }
    robot
        .section_mut("worldbody")
        .find_named_mut("body", &robot_info.root_body)
        .ok_or_else(|| SimError::Assets("robot root body vanished".into()))?
        .set("pos", array_to_string(&base));
    let mut sites = Vec::new();
    robot.section("worldbody").walk(None, &mut |e, _| {
        if e.tag == "site" {
            if let Some(n) = e.get("name") {
                sites.push(n.to_string());
            }
        }
    });
    Ok((robot, base, sites))
}

/// Arena per problem class: scene XML, recolouring, table sizing, textures, origin, cameras.
fn build_arena(class: ProblemClass, paths: &AssetPaths) -> Result<MjXml, SimError> {
    let root = if class == ProblemClass::RobosuiteDoor { &paths.robosuite_assets } else { &paths.libero_assets };
    let mut arena = MjXml::load(&root.join(class.scene_xml()))?;
    recolor_collision_geoms(arena.section_mut("worldbody"), &mjxml::ENVIRONMENT_COLLISION_COLOR, true);
    if matches!(class, ProblemClass::Tabletop | ProblemClass::Kitchen | ProblemClass::RobosuiteDoor) {
        configure_table(&mut arena, class)?;
    }
    // floor / wall textures: replace the file name, keep the directory
    let textures = class.textures().map(|(floor, wall)| [("texplane", floor), ("tex-wall", wall)]);
    for (tex, file) in textures.into_iter().flatten() {
        let node = arena
            .section_mut("asset")
            .child_named_mut("texture", tex)
            .ok_or_else(|| SimError::Assets(format!("{}: no texture `{tex}`", class.scene_xml())))?;
        let old = node.get("file").unwrap_or("").to_string();
        let mut parts: Vec<&str> = old.split('/').collect();
        parts.pop();
        parts.push(file);
        node.set("file", parts.join("/"));
    }
    // set_origin([0, 0, 0]): every direct worldbody child with a pos is re-written
    for node in &mut arena.section_mut("worldbody").children {
        if let Some(p) = node.get("pos") {
            let v: Vec<f64> = string_to_array(p)?.iter().map(|x| x + 0.0).collect();
            node.set("pos", array_to_string(&v));
        }
    }
    for cam in class.cameras() {
        let world = arena.section_mut("worldbody");
        let pos = array_to_string(&cam.pos);
        let quat = array_to_string(&cam.quat);
        match world.find_named_mut("camera", cam.name) {
            Some(c) => {
                c.set("pos", pos);
                c.set("quat", quat);
            }
            None => world.children.push(Element::with_attrs("camera", &[("pos", pos), ("quat", quat), ("name", cam.name.to_string())])),
        }
    }
    Ok(arena)
}

/// `TableArena.configure_location` / `KitchenTableArena.configure_location` (identical code; robosuite's own
/// `TableArena` is the same too, with its default friction (1, 0.005, 0.0001)).
fn configure_table(arena: &mut MjXml, class: ProblemClass) -> Result<(), SimError> {
    let full = class.table_full_size().expect("table classes have a size");
    let half = [full[0] / 2.0, full[1] / 2.0, full[2] / 2.0];
    let offset = class.workspace_offset();
    let friction: [f64; 3] = if class == ProblemClass::Tabletop { [0.6, 0.005, 0.0001] } else { [1.0, 0.005, 0.0001] };
    let friction_s = if class == ProblemClass::Tabletop {
        array_to_string(&friction)
    } else {
        "1 0.005 0.0001".to_string() // KitchenTableArena default (1, 0.005, 0.0001): Python int 1
    };
    // center_pos = bottom_pos + [0, 0, -half_z] + table_offset
    let center: Vec<f64> = (0..3).map(|k| (0.0 + if k == 2 { -half[2] } else { 0.0 }) + offset[k]).collect();
    let world = arena.section_mut("worldbody");
    if let Some(floor) = world.child_named_mut("geom", "floor") {
        floor.set("pos", array_to_string(&[0.0, 0.0, 0.0]));
    }
    let table = world
        .child_named_mut("body", "table")
        .ok_or_else(|| SimError::Assets("table arena without body `table`".into()))?;
    table.set("pos", array_to_string(&center));
    let half_s = array_to_string(&half);
    if let Some(g) = table.child_named_mut("geom", "table_collision") {
        g.set("size", half_s.clone());
        g.set("friction", friction_s);
    }
    if let Some(g) = table.child_named_mut("geom", "table_visual") {
        g.set("size", half_s);
    }
    if let Some(s) = table.child_named_mut("site", "table_top") {
        s.set("pos", array_to_string(&[0.0, 0.0, half[2]]));
    }
    let dx = [0.1, -0.1, -0.1, 0.1];
    let dy = [0.1, 0.1, -0.1, -0.1];
    for (i, (ddx, ddy)) in dx.iter().zip(dy).enumerate() {
        let name = format!("table_leg{}_visual", i + 1);
        let Some(leg) = table.child_named_mut("geom", &name) else { continue };
        let mut x = 0.0;
        if half[0] > (ddx * 2.0f64).abs() {
            x += ddx.signum() * half[0] - ddx;
        }
        let mut y = 0.0;
        if half[1] > (ddy * 2.0f64).abs() {
            y += ddy.signum() * half[1] - ddy;
        }
        let z = (offset[2] - half[2]) / 2.0;
        leg.set("pos", array_to_string(&[x, y, -z]));
        leg.set("size", array_to_string(&[0.025, z]));
    }
    Ok(())
}

/// Python `"{}".format(v)` for values that are Python ints when integral in LIBERO's defaults.
fn fmt_list_like_python(v: &[f64], ints: bool) -> String {
    if ints {
        v.iter().map(|x| format!("{}", *x as i64)).collect::<Vec<_>>().join(" ")
    } else {
        array_to_string(v)
    }
}

/// Compose a parsed problem.
pub fn compose(problem: &Problem, paths: &AssetPaths) -> Result<ComposedScene, SimError> {
    let class = ProblemClass::from_problem_name(&problem.problem_name).ok_or_else(|| {
        SimError::Input(format!(
            "unknown problem class `{}` (known: libero_tabletop_manipulation, libero_kitchen_tabletop_manipulation, \
             libero_living_room_tabletop_manipulation, libero_study_tabletop_manipulation, libero_floor_manipulation, \
             libero_coffee_table_manipulation, libero_robosuite_door_manipulation)",
            problem.problem_name
        ))
    })?;
    let (robot, robot_base_pos, robot_sites) = build_robot(class, paths)?;
    let mut arena = build_arena(class, paths)?;
    // fixtures (fixture dict order, workspace category skipped), then objects
    let lookup = |inst: &libero_bddl::Instance| {
        registry::category(&inst.category).ok_or_else(|| {
            SimError::Input(format!("unknown object category `{}` (instance `{}`)", inst.category, inst.name))
        })
    };
    let mut fixtures = Vec::new();
    for inst in &problem.fixtures {
        if inst.category == class.workspace_category() {
            continue;
        }
        fixtures.push(load_object(&inst.name, &lookup(inst)?, true, paths)?);
    }
    let mut objects = Vec::new();
    for inst in &problem.objects {
        objects.push(load_object(&inst.name, &lookup(inst)?, false, paths)?);
    }
    // regions: table zones get a site on the workspace body; others refer to an instance's site
    let ws = class.workspace_name();
    let wo = class.workspace_offset();
    let mut regions = Vec::new();
    for r in &problem.regions {
        if r.key.contains(ws) {
            let Some(rg) = r.ranges.first() else {
                return Err(SimError::Input(format!("workspace region `{}` has no (:ranges ...)", r.key)));
            };
            if !(rg[2] >= rg[0] && rg[3] >= rg[1]) {
                return Err(SimError::Input(format!("region `{}`: range must be (x_min y_min x_max y_max)", r.key)));
            }
            let size = [(rg[2] - rg[0]) / 2.0, (rg[3] - rg[1]) / 2.0, 0.007];
            let cx = (rg[2] + rg[0]) / 2.0;
            let cy = (rg[3] + rg[1]) / 2.0;
            let pos_s = match class {
                ProblemClass::Tabletop | ProblemClass::Floor | ProblemClass::CoffeeTable | ProblemClass::RobosuiteDoor => {
                    array_to_string(&[cx, cy, 0.02])
                }
                ProblemClass::Kitchen => array_to_string(&[cx + wo[0] + 0.0, cy + wo[1] + 0.0, wo[2] + -0.90]),
                ProblemClass::Study | ProblemClass::LivingRoom => array_to_string(&[cx + wo[0], cy + wo[1], wo[2]]),
            };
            let site = Element::with_attrs(
                "site",
                &[
                    ("pos", pos_s),
                    ("size", array_to_string(&size)),
                    ("rgba", fmt_list_like_python(&r.rgba, r.rgba.iter().all(|v| v.fract() == 0.0))),
                    ("quat", "1 0 0 0".into()),
                    ("type", "box".into()),
                    ("name", r.key.clone()),
                ],
            );
            let body = class.region_body();
            arena
                .section_mut("worldbody")
                .find_named_mut("body", body)
                .ok_or_else(|| SimError::Assets(format!("scene has no body `{body}` for region sites")))?
                .children
                .push(site);
            regions.push(RegionInfo {
                key: r.key.clone(),
                target: r.target.clone(),
                parent: None,
                joints: Vec::new(),
                size: size.to_vec(),
                ranges: r.ranges.clone(),
                yaw_rotation: r.yaw_rotation,
            });
            continue;
        }
        // objects_dict first, then fixtures_dict; the last match wins (dict assignment)
        let mut found: Option<RegionInfo> = None;
        for lo in objects.iter().chain(fixtures.iter()) {
            for (site, size, joints) in &lo.site_scan {
                if format!("{}_{}", lo.info.name, site) == r.key {
                    found = Some(RegionInfo {
                        key: r.key.clone(),
                        target: r.target.clone(),
                        parent: Some(lo.info.name.clone()),
                        joints: joints.clone(),
                        size: size.clone(),
                        ranges: r.ranges.clone(),
                        yaw_rotation: r.yaw_rotation,
                    });
                }
            }
        }
        // regions naming a site the target does not have are ignored, as in LIBERO
        if let Some(f) = found {
            regions.push(f);
        }
    }
    // world = base.xml + arena + robot + objects + fixtures
    let mut world = MjXml::load(&paths.robosuite_assets.join("base.xml"))?;
    if let Some(opt) = world.root.child_mut("option") {
        opt.set("timestep", py_float(0.002));
    }
    world.merge(arena, None)?;
    world.merge(robot, None)?;
    for lo in objects.iter().chain(fixtures.iter()) {
        world.merge_assets(&lo.assets);
        world.section_mut("worldbody").children.push(lo.body.clone());
        world.section_mut("sensor").children.extend(lo.sensors.children.iter().cloned());
    }
    let mjcf = world.root.to_xml();
    Ok(ComposedScene {
        bddl_file: None,
        problem_name: problem.problem_name.clone(),
        problem_class: class,
        language: problem.language.clone(),
        mjcf,
        robot_base_pos,
        robot_mounted: class.robot_is_mounted(),
        objects: objects.into_iter().map(|o| o.info).collect(),
        fixtures: fixtures.into_iter().map(|o| o.info).collect(),
        regions,
        workspace_offset: wo,
        fixture_z_offset: class.fixture_z_offset(),
        robot_sites,
        problem: problem.clone(),
    })
}

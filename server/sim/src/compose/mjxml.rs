//! robosuite 1.4 `MujocoXML` / `MujocoXMLModel` / `MujocoXMLObject` behaviour on [`Element`] trees: loading with
//! `<default>` classes inlined and asset paths made absolute, default geom names, name prefixing, collision-geom
//! recolouring and merging. Each function names the robosuite method it reproduces.
use std::path::{Path, PathBuf};

use super::xml::{array_to_string, parse_file, string_to_array, Element};
use crate::SimError;

/// The sections `MujocoXML.__init__` creates (in this order) when the file lacks them.
const DEFAULT_SECTIONS: [&str; 7] = ["worldbody", "actuator", "sensor", "asset", "tendon", "equality", "contact"];

/// robosuite `MUJOCO_NAMED_ATTRIBUTES`: attributes that hold names and get the model prefix.
const NAMED_ATTRIBUTES: [&str; 28] = [
    "class", "childclass", "name", "objname", "material", "texture", "joint", "joint1", "joint2", "jointinparent",
    "geom", "geom1", "geom2", "mesh", "fixed", "actuator", "tendon", "tendon1", "tendon2", "slidesite", "cranksite",
    "body", "body1", "body2", "hfield", "target", "prefix", "site",
];

pub const ROBOT_COLLISION_COLOR: [f64; 4] = [0.0, 0.5, 0.0, 1.0];
pub const MOUNT_COLLISION_COLOR: [f64; 4] = [0.5, 0.5, 0.0, 1.0];
pub const GRIPPER_COLLISION_COLOR: [f64; 4] = [0.0, 0.0, 0.5, 1.0];
pub const ENVIRONMENT_COLLISION_COLOR: [f64; 4] = [0.5, 0.5, 0.0, 1.0];

/// A loaded MJCF document (`MujocoXML`).
#[derive(Debug, Clone)]
pub struct MjXml {
    pub root: Element,
    pub file: PathBuf,
}

/// robosuite's `array_to_string` of ints writes `0`, of floats `0.0`; colours are given as Python lists mixing both.
fn color_string(rgba: &[f64; 4]) -> String {
    rgba.iter()
        .map(|v| if v.fract() == 0.0 { format!("{}", *v as i64) } else { super::xml::py_float(*v) })
        .collect::<Vec<_>>()
        .join(" ")
}

impl MjXml {
    /// `MujocoXML.__init__`: parse, create missing sections, inline `<default>` classes (one level, as robosuite
    /// does), delete `<default>`, make every `<asset>` child's `file` absolute (os.path.join semantics).
    pub fn load(path: &Path) -> Result<Self, SimError> {
        let mut root = parse_file(path)?;
        for tag in DEFAULT_SECTIONS.iter().chain(std::iter::once(&"default")) {
            if root.child(tag).is_none() {
                root.children.push(Element::new(tag));
            }
        }
        // _get_default_classes: {class: {child.tag: child}} over the direct children of the first <default>
        let default = root.child("default").cloned().unwrap_or_else(|| Element::new("default"));
        let mut classes: Vec<(Option<String>, Vec<Element>)> = Vec::new();
        for cls in &default.children {
            let key = cls.get("class").map(str::to_string);
            let mut templates: Vec<Element> = Vec::new();
            for t in &cls.children {
                // dict comprehension: a repeated tag keeps the last template
                if let Some(slot) = templates.iter_mut().find(|x| x.tag == t.tag) {
                    *slot = t.clone();
                } else {
                    templates.push(t.clone());
                }
            }
            if let Some(slot) = classes.iter_mut().find(|(k, _)| *k == key) {
                slot.1 = templates;
            } else {
                classes.push((key, templates));
            }
        }
        let mut missing: Option<String> = None;
        root.walk_mut(None, &mut |e, _| {
            if let Some(cls) = e.remove_attr("class") {
                match classes.iter().find(|(k, _)| k.as_deref() == Some(cls.as_str())) {
                    Some((_, templates)) => {
                        if let Some(t) = templates.iter().find(|t| t.tag == e.tag) {
                            for (k, v) in &t.attrs {
                                if e.get(k).is_none() {
                                    e.set(k, v.clone());
                                }
                            }
                        }
                    }
                    None => missing = Some(cls),
                }
            }
        });
        if let Some(cls) = missing {
            return Err(SimError::Assets(format!(
                "{}: default class `{cls}` is not defined at the first level of <default> (robosuite cannot load it either)",
                path.display()
            )));
        }
        if let Some(i) = root.children.iter().position(|c| c.tag == "default") {
            root.children.remove(i);
        }
        let folder = path.parent().map(Path::to_path_buf).unwrap_or_default();
        let folder = std::path::absolute(&folder).unwrap_or(folder);
        if let Some(asset) = root.child_mut("asset") {
            for node in &mut asset.children {
                if let Some(file) = node.get("file") {
                    let joined = if file.starts_with('/') {
                        file.to_string()
                    } else {
                        format!("{}/{}", folder.to_string_lossy().trim_end_matches('/'), file)
                    };
                    node.set("file", joined);
                }
            }
        }
        Ok(Self { root, file: path.to_path_buf() })
    }

    pub fn section(&self, tag: &str) -> &Element {
        self.root.child(tag).expect("MjXml::load creates every default section")
    }

    pub fn section_mut(&mut self, tag: &str) -> &mut Element {
        self.root.child_mut(tag).expect("MjXml::load creates every default section")
    }

    /// `MujocoXML.merge_assets`: append each asset unless one with the same tag and name exists.
    pub fn merge_assets(&mut self, assets: &Element) {
        let mine = self.section_mut("asset");
        for a in &assets.children {
            let name = a.get("name");
            // find_elements with attribs={"name": None} matches elements without a name
            let exists = mine.children.iter().any(|m| m.tag == a.tag && m.get("name") == name);
            if !exists {
                mine.children.push(a.clone());
            }
        }
    }

    /// `MujocoXML.merge(other, merge_body)`: worldbody children go to the world (`None`) or into the named body.
    pub fn merge(&mut self, other: MjXml, merge_body: Option<&str>) -> Result<(), SimError> {
        let other_world = other.section("worldbody").children.clone();
        match merge_body {
            None => self.section_mut("worldbody").children.extend(other_world),
            Some(body) => {
                let target = self
                    .section_mut("worldbody")
                    .find_named_mut("body", body)
                    .ok_or_else(|| SimError::Input(format!("merge target body `{body}` not found")))?;
                target.children.extend(other_world);
            }
        }
        self.merge_assets(other.section("asset"));
        for tag in ["actuator", "sensor", "tendon", "equality", "contact"] {
            let items = other.section(tag).children.clone();
            self.section_mut(tag).children.extend(items);
        }
        Ok(())
    }
}

/// `recolor_collision_geoms`: geoms of group None/"0" get `rgba` and lose their material.
pub fn recolor_collision_geoms(root: &mut Element, rgba: &[f64; 4], exclude_floor: bool) {
    let color = color_string(rgba);
    root.walk_mut(None, &mut |e, _| {
        if e.tag == "geom"
            && matches!(e.get("group"), None | Some("0"))
            && !(exclude_floor && e.get("name") == Some("floor"))
        {
            e.set("rgba", color.clone());
            e.remove_attr("material");
        }
    });
}

/// `add_prefix` with the default attribute set (values already starting with the prefix are left alone).
pub fn add_prefix(root: &mut Element, prefix: &str) {
    root.walk_mut(None, &mut |e, _| {
        for (k, v) in e.attrs.iter_mut() {
            if NAMED_ATTRIBUTES.contains(&k.as_str()) && !v.starts_with(prefix) {
                *v = format!("{prefix}{v}");
            }
        }
    });
}

/// What `sort_elements` finds in a robot/gripper/mount model (names before prefixing are not needed).
#[derive(Debug, Clone, Default)]
pub struct ModelInfo {
    pub root_body: String,
    /// `pos` of the root body as written in the file (robosuite `base_offset`).
    pub base_offset: [f64; 3],
}

/// `MujocoXMLModel.__init__`: name unnamed geoms `g{k}_col`/`g{k}_vis` (one counter per kind, document order
/// over the whole file), read the root body and its offset, prefix every name, recolour collision geoms.
pub fn prepare_model(xml: &mut MjXml, prefix: &str, collision_rgba: &[f64; 4]) -> Result<ModelInfo, SimError> {
    let (mut col, mut vis) = (0usize, 0usize);
    let mut bad_group: Option<String> = None;
    xml.root.walk_mut(None, &mut |e, _| {
        if e.tag == "geom" && e.get("name").is_none() {
            match e.get("group") {
                None | Some("0") => {
                    e.set("name", format!("g{col}_col"));
                    col += 1;
                }
                Some("1") => {
                    e.set("name", format!("g{vis}_vis"));
                    vis += 1;
                }
                Some(g) => bad_group = Some(g.to_string()),
            }
        }
    });
    if let Some(g) = bad_group {
        return Err(SimError::Assets(format!("{}: unnamed geom in group {g} (robosuite only names groups 0/1)", xml.file.display())));
    }
    let world = xml.section("worldbody");
    let root_body = world
        .children
        .iter()
        .find(|c| c.tag == "body")
        .ok_or_else(|| SimError::Assets(format!("{}: no root body", xml.file.display())))?;
    let pos = string_to_array(root_body.get("pos").unwrap_or("0 0 0"))?;
    let base_offset = [pos[0], pos[1], pos[2]];
    let root_name = root_body.get("name").unwrap_or("").to_string();
    add_prefix(&mut xml.root, prefix);
    recolor_collision_geoms(xml.section_mut("worldbody"), collision_rgba, false);
    Ok(ModelInfo { root_body: format!("{prefix}{root_name}"), base_offset })
}

/// Robot joints as `sort_elements` lists them: `<joint>` elements outside `<actuator>` without `joint`/`joint1`.
pub fn robot_joints_mut(root: &mut Element) -> Vec<&mut Element> {
    fn collect<'a>(e: &'a mut Element, parent_is_actuator: bool, out: &mut Vec<&'a mut Element>) {
        let is_joint = !parent_is_actuator && e.tag == "joint" && e.get("joint").is_none() && e.get("joint1").is_none();
        let is_act = e.tag == "actuator";
        if is_joint {
            out.push(e);
            return;
        }
        for c in &mut e.children {
            collect(c, is_act, out);
        }
    }
    let mut out = Vec::new();
    collect(root, false, &mut out);
    out
}

/// `RobotModel.set_joint_attribute(attrib, values, force)`.
pub fn set_joint_attribute(root: &mut Element, attrib: &str, values: &[f64], force: bool) -> Result<(), SimError> {
    let mut joints = robot_joints_mut(root);
    if joints.len() != values.len() {
        return Err(SimError::Assets(format!("robot has {} joints, expected {}", joints.len(), values.len())));
    }
    for (j, v) in joints.iter_mut().zip(values) {
        if force || j.get(attrib).is_none() {
            j.set(attrib, array_to_string(&[*v]));
        }
    }
    Ok(())
}


//! LIBERO's object registry (hf-libero 0.1.4 `envs/objects/*.py`): category key → asset file, placement rotation
//! and articulation ranges. The values are those of the Python classes.
use std::f64::consts::{FRAC_PI_2, FRAC_PI_4};

/// How a placement sampler draws an object's orientation.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub enum Rotation {
    /// `(min, max)` about one axis (`x`, `y` or `z`).
    Range { range: [f64; 2], axis: char },
    /// Per-axis ranges composed in this order (LIBERO's dict rotations, e.g. ketchup `{x: .., z: ..}`).
    Composed(Vec<(char, [f64; 2])>),
}

/// Joint-range defaults used by `Open`/`Close`/`TurnOn`/`TurnOff` initial conditions and predicates.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Articulation {
    pub open: Option<[f64; 2]>,
    pub close: Option<[f64; 2]>,
    pub turn_on: Option<[f64; 2]>,
    pub turn_off: Option<[f64; 2]>,
}

/// Which tree a category's file is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum AssetRoot {
    /// The LIBERO asset set (`AssetPaths::libero_assets`).
    Libero,
    /// The repository's `assets/` (`AssetPaths::project_assets`): objects authored for this project.
    Project,
}

/// One registered category.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Category {
    pub key: &'static str,
    /// Path relative to `root`.
    pub file: String,
    pub root: AssetRoot,
    pub rotation: Rotation,
    /// `Some` for articulated objects (`ArticulatedObject` subclasses).
    pub articulation: Option<Articulation>,
    /// `BasinFaucet` is the one class that never gets a free joint.
    pub free_joint_as_object: bool,
    /// Sites whose visibility follows the object state (flat_stove `burner`).
    pub vis_sites: &'static [&'static str],
    /// `Some`: only these joints (unprefixed names) are the instance's articulation joints that predicates and
    /// `Open`/`Close` initializers read; the others (the latched door's latch) only act physically.
    pub exposed_joints: Option<&'static [&'static str]>,
    /// Edits applied to `file` at compose time (derived categories, see [`DERIVED`]); empty for plain categories.
    pub edits: &'static [AssetEdit],
}

/// One declared edit of a category's MJCF, applied to the loaded tree before prefixing. Elements are found by tag and
/// name anywhere in the asset's outer body; unnamed geoms of the `object` body are named `g<i>` (document order over
/// all its geoms) before the edits run, as the loader names them anyway.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub enum AssetEdit {
    /// Replace attribute `attr` of `<tag name=name>`, which must currently read `from` (guards against an asset
    /// update silently changing what the edit means).
    Set { tag: &'static str, name: &'static str, attr: &'static str, from: &'static str, to: &'static str },
    /// Append `<tag attrs…/>` to the body named `body`.
    Add { body: &'static str, tag: &'static str, attrs: &'static [(&'static str, &'static str)] },
}

/// Categories derived from a LIBERO category by declared edits (RoboMemArena's asset variants, task catalog §6.9):
/// the LIBERO file in the asset cache is loaded and edited at compose time, so no LIBERO mesh or MJCF is copied
/// into the repository. Key, base category, edits; everything else (rotation, articulation) is the base's.
/// Close range of the raised cabinet's slides: LIBERO's `[0, 0.005]` capped below the slide value (≈ 0.0025 m) past
/// which the bottom drawer's front panel, whose top edge overlaps the shelf above it by 0.6 mm in the LIBERO asset,
/// slides under that shelf's front edge; that stiff contact (solref 0.001) then presses with ≈ 0.3 MN and the drawer
/// does not move under a 10 kN pull, so a task that must open it could never be solved from such a start.
pub const TALL_CABINET_CLOSE_RANGE_M: [f64; 2] = [0.0, 0.002];

const DERIVED: &[(&str, &str, &[AssetEdit])] = &[
    // T23, T27: the wooden cabinet raised 5 cm on a visual plinth; drawers, joints and sites unchanged relative to
    // the raised body (roof site `top_side` ends at z 0.27152)
    (
        "wooden_cabinet_tall_bottom",
        "wooden_cabinet",
        &[
            AssetEdit::Set { tag: "body", name: "base", attr: "pos", from: "0 0 0.0", to: "0 0 0.05" },
            AssetEdit::Add {
                body: "object",
                tag: "geom",
                attrs: &[
                    ("name", "plinth"),
                    ("type", "box"),
                    ("pos", "0.004 0.016 0.025"),
                    ("size", "0.12534 0.09438 0.025"),
                    ("contype", "0"),
                    ("conaffinity", "0"),
                    ("group", "1"),
                    ("material", "wooden_cabinet_base"),
                ],
            },
        ],
    ),
    // pool vlabench_physical/2 (active_weight_comparison): T30's seesaw primitive with its far-end region marked (a
    // yellow band wrapping the plank over `seesaw_right_region` and the far lip painted yellow, visual only: the head
    // camera sees the tilted board nearly edge-on, so it sees the lip) and its hinge spring scaled by the light
    // weight's mass over T30's counterweight's (0.6 × 0.30 / 0.08 = 2.25 N·m/rad): the 0.30 kg weight alone tilts the
    // board part way, as one counterweight tilts T30's, and the 1.20 kg one to the stop; on T30's spring both reach the
    // 0.6 rad stop and their responses differ only by the stop's softness (tasks/README.md)
    (
        "vlabench_seesaw_marked",
        "vlabench_seesaw",
        &[
            AssetEdit::Set { tag: "joint", name: "seesaw_hinge", attr: "stiffness", from: "0.6", to: "2.25" },
            AssetEdit::Add {
                body: "board",
                tag: "geom",
                attrs: &[
                    ("name", "far_end_mark_visual"),
                    ("type", "box"),
                    ("size", "0.055 0.0502 0.0016"),
                    ("pos", "0.24 0 0"),
                    ("rgba", "0.95 0.78 0.12 1"),
                    ("group", "1"),
                    ("contype", "0"),
                    ("conaffinity", "0"),
                    ("mass", "0"),
                ],
            },
            AssetEdit::Add {
                body: "board",
                tag: "geom",
                attrs: &[
                    ("name", "far_lip_mark_visual"),
                    ("type", "box"),
                    ("size", "0.0026 0.0502 0.0204"),
                    ("pos", "0.30 0 0.02"),
                    ("rgba", "0.95 0.78 0.12 1"),
                    ("group", "1"),
                    ("contype", "0"),
                    ("conaffinity", "0"),
                    ("mass", "0"),
                ],
            },
        ],
    ),
    // T24: the chefmate frypan with its flat base collision box (geom 4) lowered 8 mm and its bottom site at
    // z −0.0112, so the pan rests on its base on the coffee table
    (
        "robomemarena_frypan",
        "chefmate_8_frypan",
        &[
            AssetEdit::Set { tag: "geom", name: "g4", attr: "pos", from: "-0.00000 -0.00000 0.00675", to: "0 0 -0.00125" },
            AssetEdit::Set { tag: "site", name: "bottom_site", attr: "pos", from: "0 0 -0.06", to: "0 0 -0.0112" },
        ],
    ),
];

const HOPE: &[&str] = &[
    "alphabet_soup", "bbq_sauce", "butter", "chocolate_pudding", "cookies", "cream_cheese", "ketchup",
    "macaroni_and_cheese", "milk", "orange_juice", "popcorn", "salad_dressing", "new_salad_dressing", "tomato_sauce",
];
const SCANNED: &[&str] = &["white_bowl", "akita_black_bowl", "plate", "basket", "chefmate_8_frypan", "glazed_rim_porcelain_ramekin"];
/// The long-horizon cooking scene's frying pan: the chefmate mesh with its own placement rotation.
pub const LONG_HORIZON_FRYPAN: &str = "long_horizon_frypan";
const TURBOSQUID: &[&str] = &[
    "wooden_tray", "white_storage_box", "wooden_shelf", "wooden_two_layer_shelf", "wine_rack", "wine_bottle",
    "dining_set_group", "bowl_drainer", "moka_pot", "black_book", "yellow_book", "red_coffee_mug", "desk_caddy",
    "porcelain_mug", "white_yellow_mug",
];
const ARTICULATED: &[&str] = &[
    "microwave", "slide_cabinet", "window", "faucet", "basin_faucet", "short_cabinet", "short_fridge",
    "wooden_cabinet", "white_cabinet", "flat_stove",
];

/// Categories authored for this project in `assets/` (objects the LIBERO set lacks): key, file under
/// `assets/`, and the fixed rotation about z the placement sampler gives movable instances (0 for all of the
/// release's repository-owned objects, task catalog §2.3). Each file follows LIBERO's object layout: an outer body
/// holding a body named `object`, with `bottom_site`, `top_site` and `horizontal_radius_site`.
const PROJECT: &[(&str, &str, f64)] = &[
    // T13: the VLABench-style single press button (task catalog §6.4)
    ("vlabench_single_button", "objects/vlabench_single_button/vlabench_single_button.xml", 0.0),
    // T18: primitive stand-ins for VLABench's chemistry tube and tube rack (catalog §4 T18, §6.8)
    ("vlabench_tube", "objects/vlabench_tube/vlabench_tube.xml", 0.0),
    ("vlabench_tube_stand", "objects/vlabench_tube_stand/vlabench_tube_stand.xml", 0.0),
    // pool vlabench_tube_precision/1: the green tube and the NameTag rack with VLABench's hole layout, written by
    // scripts/gen_perception_assets.py
    ("vlabench_green_tube", "objects/vlabench_green_tube/vlabench_green_tube.xml", 0.0),
    ("vlabench_tube_stand_tagged", "objects/vlabench_tube_stand_tagged/vlabench_tube_stand_tagged.xml", 0.0),
    // T19 (task catalog §6.6): RoboCasa-style sponge (movable) and tabletop spill patch with the blue rest pad (fixture)
    ("robocasa_sponge", "objects/robocasa_sponge/robocasa_sponge.xml", 0.0),
    ("robocasa_spill_patch", "objects/robocasa_spill_patch/robocasa_spill_patch.xml", 0.0),
    // T01, T03, T04, T05, T07 (task catalog §3.0, §6.5): the collection bin and the primitive candidates, written by
    // scripts/gen_perception_assets.py
    ("vlabench_perception_bin", "objects/vlabench_perception_bin/vlabench_perception_bin.xml", 0.0),
    ("vlabench_perception_upright_token", "objects/vlabench_perception_upright_token/vlabench_perception_upright_token.xml", 0.0),
    ("vlabench_perception_fallen_token", "objects/vlabench_perception_fallen_token/vlabench_perception_fallen_token.xml", 0.0),
    ("vlabench_perception_fallen_token_2", "objects/vlabench_perception_fallen_token_2/vlabench_perception_fallen_token_2.xml", 0.0),
    ("vlabench_perception_red_color", "objects/vlabench_perception_red_color/vlabench_perception_red_color.xml", 0.0),
    ("vlabench_perception_blue_color", "objects/vlabench_perception_blue_color/vlabench_perception_blue_color.xml", 0.0),
    ("vlabench_perception_green_color", "objects/vlabench_perception_green_color/vlabench_perception_green_color.xml", 0.0),
    ("vlabench_perception_striped_texture", "objects/vlabench_perception_striped_texture/vlabench_perception_striped_texture.xml", 0.0),
    ("vlabench_perception_spotted_texture", "objects/vlabench_perception_spotted_texture/vlabench_perception_spotted_texture.xml", 0.0),
    ("vlabench_perception_plain_texture", "objects/vlabench_perception_plain_texture/vlabench_perception_plain_texture.xml", 0.0),
    ("vlabench_perception_single_marked_instance", "objects/vlabench_perception_single_marked_instance/vlabench_perception_single_marked_instance.xml", 0.0),
    ("vlabench_perception_double_marked_instance", "objects/vlabench_perception_double_marked_instance/vlabench_perception_double_marked_instance.xml", 0.0),
    ("vlabench_perception_unmarked_instance", "objects/vlabench_perception_unmarked_instance/vlabench_perception_unmarked_instance.xml", 0.0),
    ("vlabench_milk_drink", "objects/vlabench_milk_drink/vlabench_milk_drink.xml", 0.0),
    ("vlabench_cola_drink", "objects/vlabench_cola_drink/vlabench_cola_drink.xml", 0.0),
    ("vlabench_juice_drink", "objects/vlabench_juice_drink/vlabench_juice_drink.xml", 0.0),
    // pool suite vlabench_world_knowledge: condiments, fruits and solutions as primitives (scripts/gen_perception_assets.py)
    ("vlabench_sugar_condiment", "objects/vlabench_sugar_condiment/vlabench_sugar_condiment.xml", 0.0),
    ("vlabench_salt_condiment", "objects/vlabench_salt_condiment/vlabench_salt_condiment.xml", 0.0),
    ("vlabench_hotsauce_condiment", "objects/vlabench_hotsauce_condiment/vlabench_hotsauce_condiment.xml", 0.0),
    ("vlabench_orange_fruit", "objects/vlabench_orange_fruit/vlabench_orange_fruit.xml", 0.0),
    ("vlabench_apple_fruit", "objects/vlabench_apple_fruit/vlabench_apple_fruit.xml", 0.0),
    ("vlabench_pear_fruit", "objects/vlabench_pear_fruit/vlabench_pear_fruit.xml", 0.0),
    // pool suite vlabench_additional/find_unseen_object: the apple small enough for a wooden-cabinet drawer
    ("vlabench_hidden_apple", "objects/vlabench_hidden_apple/vlabench_hidden_apple.xml", 0.0),
    ("vlabench_blue_solution", "objects/vlabench_blue_solution/vlabench_blue_solution.xml", 0.0),
    ("vlabench_green_solution", "objects/vlabench_green_solution/vlabench_green_solution.xml", 0.0),
    ("vlabench_clear_solution", "objects/vlabench_clear_solution/vlabench_clear_solution.xml", 0.0),
    // pool vlabench_additional/cluster_series: the banana as a primitive (VLABench's banana family is excluded as buggy)
    ("vlabench_banana_fruit", "objects/vlabench_banana_fruit/vlabench_banana_fruit.xml", 0.0),
    // T06, T09, T10 (task catalog §3.1, §6.4): buttons paired with a candidate cue, written by
    // scripts/gen_perception_assets.py
    ("vlabench_property_weight_sphere", "objects/vlabench_property_weight_sphere/vlabench_property_weight_sphere.xml", 0.0),
    ("vlabench_property_weight_cylinder", "objects/vlabench_property_weight_cylinder/vlabench_property_weight_cylinder.xml", 0.0),
    ("vlabench_property_weight_cube", "objects/vlabench_property_weight_cube/vlabench_property_weight_cube.xml", 0.0),
    ("vlabench_property_size_small_cylinder", "objects/vlabench_property_size_small_cylinder/vlabench_property_size_small_cylinder.xml", 0.0),
    ("vlabench_property_size_medium_cylinder", "objects/vlabench_property_size_medium_cylinder/vlabench_property_size_medium_cylinder.xml", 0.0),
    ("vlabench_property_size_large_cylinder", "objects/vlabench_property_size_large_cylinder/vlabench_property_size_large_cylinder.xml", 0.0),
    ("vlabench_property_reflection_matte_gray", "objects/vlabench_property_reflection_matte_gray/vlabench_property_reflection_matte_gray.xml", 0.0),
    ("vlabench_property_reflection_polished_silver", "objects/vlabench_property_reflection_polished_silver/vlabench_property_reflection_polished_silver.xml", 0.0),
    ("vlabench_property_reflection_satin_gray", "objects/vlabench_property_reflection_satin_gray/vlabench_property_reflection_satin_gray.xml", 0.0),
    // pool suite vlabench_button, tasks 0-5 (the question-bank buttons; task 6 uses T09's panels): the same button with
    // the candidate each question names, written by scripts/gen_perception_assets.py
    ("vlabench_property_density_rubber", "objects/vlabench_property_density_rubber/vlabench_property_density_rubber.xml", 0.0),
    ("vlabench_property_density_glass", "objects/vlabench_property_density_glass/vlabench_property_density_glass.xml", 0.0),
    ("vlabench_property_density_steel", "objects/vlabench_property_density_steel/vlabench_property_density_steel.xml", 0.0),
    ("vlabench_property_magnetism_wood", "objects/vlabench_property_magnetism_wood/vlabench_property_magnetism_wood.xml", 0.0),
    ("vlabench_property_magnetism_steel", "objects/vlabench_property_magnetism_steel/vlabench_property_magnetism_steel.xml", 0.0),
    ("vlabench_property_magnetism_glass", "objects/vlabench_property_magnetism_glass/vlabench_property_magnetism_glass.xml", 0.0),
    ("vlabench_property_friction_ptfe", "objects/vlabench_property_friction_ptfe/vlabench_property_friction_ptfe.xml", 0.0),
    ("vlabench_property_friction_wood", "objects/vlabench_property_friction_wood/vlabench_property_friction_wood.xml", 0.0),
    ("vlabench_property_friction_rubber", "objects/vlabench_property_friction_rubber/vlabench_property_friction_rubber.xml", 0.0),
    ("vlabench_property_thermal_fused_silica", "objects/vlabench_property_thermal_fused_silica/vlabench_property_thermal_fused_silica.xml", 0.0),
    ("vlabench_property_thermal_steel", "objects/vlabench_property_thermal_steel/vlabench_property_thermal_steel.xml", 0.0),
    ("vlabench_property_thermal_aluminium", "objects/vlabench_property_thermal_aluminium/vlabench_property_thermal_aluminium.xml", 0.0),
    ("vlabench_property_sound_rubber", "objects/vlabench_property_sound_rubber/vlabench_property_sound_rubber.xml", 0.0),
    ("vlabench_property_sound_glass", "objects/vlabench_property_sound_glass/vlabench_property_sound_glass.xml", 0.0),
    ("vlabench_property_sound_steel", "objects/vlabench_property_sound_steel/vlabench_property_sound_steel.xml", 0.0),
    ("vlabench_property_mass_wood_ball", "objects/vlabench_property_mass_wood_ball/vlabench_property_mass_wood_ball.xml", 0.0),
    ("vlabench_property_mass_wood_cube", "objects/vlabench_property_mass_wood_cube/vlabench_property_mass_wood_cube.xml", 0.0),
    ("vlabench_property_mass_wood_cylinder", "objects/vlabench_property_mass_wood_cylinder/vlabench_property_mass_wood_cylinder.xml", 0.0),
    // T08 (task catalog §6.3): one weighing-mug category for all three mugs (masses are private, set per episode) and
    // the green target bin, written by scripts/gen_perception_assets.py
    ("clier_weighing_mug", "objects/clier_weighing_mug/clier_weighing_mug.xml", 0.0),
    ("composuite_target_bin", "objects/composuite_target_bin/composuite_target_bin.xml", 0.0),
    // T28 (task catalog §6.7): robosuite's locked door (`door_lock.xml`) with the LIBERO wrapper's hinge overrides
    (LATCHED_DOOR, "objects/robosuite_latched_door/robosuite_latched_door.xml", 0.0),
    // T29 (task catalog §6.2): MetaWorld-style hammer (movable) and nail block with the sliding nail (fixture; no
    // predicate reads the nail joint, the private evaluator does)
    ("metaworld_hammer", "objects/metaworld_hammer/metaworld_hammer.xml", 0.0),
    ("metaworld_hammer_block", "objects/metaworld_hammer_block/metaworld_hammer_block.xml", 0.0),
    // pool task long_horizon_v2/2 (task catalog §6.2): the MetaWorld-style coffee machine, primitives (fixture; the
    // brew button's slide joint is read by the private evaluator only)
    ("metaworld_coffee_machine", "objects/metaworld_coffee_machine/metaworld_coffee_machine.xml", 0.0),
    // T30 (task catalog §6.1): the VLABench seesaw primitive (fixture; hinge `seesaw_hinge`, far-end site
    // `seesaw_right_region`) and its 0.08 kg counterweight
    ("vlabench_seesaw", "objects/vlabench_seesaw/vlabench_seesaw.xml", 0.0),
    ("vlabench_seesaw_weight", "objects/vlabench_seesaw_weight/vlabench_seesaw_weight.xml", 0.0),
    // pool suite vlabench_physical, tasks 1 and 2 (catalog §6.1, `seesaw_weight_light/medium/heavy.xml`): one neutral
    // weight for all three variants (same envelope; masses are private, set per episode)
    ("vlabench_seesaw_mass_weight", "objects/vlabench_seesaw_mass_weight/vlabench_seesaw_mass_weight.xml", 0.0),
];

/// The latched door fixture of T28: only its `hinge` is an articulation joint (catalog §2.2).
pub const LATCHED_DOOR: &str = "robosuite_latched_door";

/// All category keys LIBERO registers (except `target_zone`, which is not an asset) and whose assets exist.
pub fn all_keys() -> Vec<&'static str> {
    let mut v: Vec<&'static str> = Vec::new();
    v.extend(HOPE);
    v.push("rack");
    v.extend(SCANNED);
    v.push(LONG_HORIZON_FRYPAN);
    v.extend(ARTICULATED);
    v.extend(TURBOSQUID);
    v
}

fn range(a: f64, b: f64, axis: char) -> Rotation {
    Rotation::Range { range: [a, b], axis }
}

/// Look a category up; `None` if LIBERO does not register it (or registers it without an asset).
pub fn category(key: &str) -> Option<Category> {
    let half_pi = range(FRAC_PI_2, FRAC_PI_2, 'x');
    let composed = Rotation::Composed(vec![('x', [FRAC_PI_2, FRAC_PI_2]), ('z', [FRAC_PI_2, FRAC_PI_2])]);
    let zero = |axis| range(0.0, 0.0, axis);
    let mk = |key: &'static str, file: String, rotation: Rotation| Category {
        key,
        file,
        rotation,
        root: AssetRoot::Libero,
        articulation: None,
        free_joint_as_object: true,
        vis_sites: &[],
        exposed_joints: None,
        edits: &[],
    };
    if let Some(&(k, base, edits)) = DERIVED.iter().find(|(k, _, _)| *k == key) {
        return category(base).map(|c| {
            let mut c = Category { key: k, edits, ..c };
            if k == "wooden_cabinet_tall_bottom"
                && let Some(a) = c.articulation.as_mut()
            {
                a.close = Some(TALL_CABINET_CLOSE_RANGE_M);
            }
            c
        });
    }
    if let Some(&(k, file, rotation_z)) = PROJECT.iter().find(|(k, _, _)| *k == key) {
        let mut c = Category { root: AssetRoot::Project, ..mk(k, file.to_owned(), range(rotation_z, rotation_z, 'z')) };
        if k == LATCHED_DOOR {
            // catalog §2.2: open range [0.31, 0.39], close range [0, 0] on the hinge (range [0, 0.4] rad)
            c.articulation = Some(Articulation { open: Some([0.31, 0.39]), close: Some([0.0, 0.0]), ..Default::default() });
            c.exposed_joints = Some(&["hinge"]);
        }
        return Some(c);
    }
    if let Some(k) = HOPE.iter().find(|k| **k == key) {
        let rot = match *k {
            "alphabet_soup" | "tomato_sauce" => range(FRAC_PI_2, FRAC_PI_2, 'z'),
            "butter" | "chocolate_pudding" | "cream_cheese" | "popcorn" => zero('x'),
            "ketchup" | "macaroni_and_cheese" | "milk" | "orange_juice" | "salad_dressing" | "new_salad_dressing" => composed,
            _ => half_pi,
        };
        return Some(mk(k, format!("stable_hope_objects/{k}/{k}.xml"), rot));
    }
    if key == "rack" {
        return Some(mk("rack", "stable_scanned_objects/simple_rack/simple_rack.xml".into(), zero('x')));
    }
    if key == LONG_HORIZON_FRYPAN {
        // T21/T22 (task catalog §5.0): LIBERO's chefmate frypan sampled with zero rotation about z. Written as
        // LIBERO writes sampler quaternions (x, y, z, w into w, x, y, z), that is a half turn about z: the handle,
        // along the mesh's +x, points toward the robot.
        return Some(mk(LONG_HORIZON_FRYPAN, "stable_scanned_objects/chefmate_8_frypan/chefmate_8_frypan.xml".into(), zero('z')));
    }
    if let Some(k) = SCANNED.iter().find(|k| **k == key) {
        return Some(mk(k, format!("stable_scanned_objects/{k}/{k}.xml"), half_pi));
    }
    if let Some(k) = TURBOSQUID.iter().find(|k| **k == key) {
        let rot = match *k {
            "white_storage_box" => zero('y'),
            "black_book" | "yellow_book" => range(-FRAC_PI_2, -FRAC_PI_4, 'x'),
            "red_coffee_mug" | "porcelain_mug" | "white_yellow_mug" => range(-FRAC_PI_2, -FRAC_PI_2, 'x'),
            _ => zero('x'),
        };
        return Some(mk(k, format!("turbosquid_objects/{k}/{k}.xml"), rot));
    }
    if let Some(k) = ARTICULATED.iter().find(|k| **k == key) {
        let mut c = mk(k, format!("articulated_objects/{k}.xml"), range(FRAC_PI_4, FRAC_PI_2, 'x'));
        let mut a = Articulation::default();
        match *k {
            "microwave" => {
                a.open = Some([-2.094, -1.3]);
                a.close = Some([-0.005, 0.0]);
            }
            "short_cabinet" => {
                a.open = Some([0.10, 0.16]);
                a.close = Some([-0.005, 0.0]);
            }
            "short_fridge" => {
                a.open = Some([2.0, 2.7]);
                a.close = Some([-0.005, 0.0]);
            }
            "wooden_cabinet" | "white_cabinet" => {
                a.open = Some([-0.16, -0.14]);
                a.close = Some([0.0, 0.005]);
            }
            "flat_stove" => {
                c.rotation = zero('y');
                a.turn_on = Some([0.5, 2.1]);
                a.turn_off = Some([-0.005, 0.0]);
                c.vis_sites = &["burner"];
            }
            "basin_faucet" => c.free_joint_as_object = false,
            _ => {}
        }
        c.articulation = Some(a);
        return Some(c);
    }
    None
}

//! LIBERO BDDL parser (no simulator dependency).
//!
//! Reproduces what LIBERO's `robosuite_parse_problem` (hf-libero 0.1.4 `envs/bddl_utils.py`, built on bddl 1.0.1
//! `scan_tokens`) extracts from a problem file, including its quirks, because the order of objects, fixtures and
//! regions decides the MuJoCo model layout (qpos order, site order):
//! * comments (`;` to end of line) are dropped and the whole text is lower-cased before tokenising;
//! * sections are processed from the *last* to the first (LIBERO pops them off the end);
//! * typed lists (`a b - type`) map each TYPE to its names; the dict order is the first appearance of a TYPE, and a
//!   TYPE repeated inside one section replaces the earlier group (Python dict assignment);
//! * a region's key is `<target>_<name>`; `:yaw_rotation` keeps the last pair; unknown region attributes are errors.
//!
//! Errors carry the file (when parsed from one), line and column.
use std::fmt;
use std::path::{Path, PathBuf};

mod sexpr;
pub use sexpr::{Pos, SExpr};

/// A parse failure with its location.
#[derive(Debug, thiserror::Error)]
pub struct BddlError {
    /// Source file, when the text came from one.
    pub file: Option<PathBuf>,
    /// 1-based line and column of the offending token (0 when not applicable).
    pub line: usize,
    pub column: usize,
    pub message: String,
}

impl fmt::Display for BddlError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let file = self.file.as_ref().map(|p| p.display().to_string()).unwrap_or_else(|| "<bddl>".into());
        if self.line > 0 {
            write!(f, "{file}:{}:{}: {}", self.line, self.column, self.message)
        } else {
            write!(f, "{file}: {}", self.message)
        }
    }
}

impl BddlError {
    fn at(pos: Pos, message: impl Into<String>) -> Self {
        Self { file: None, line: pos.line, column: pos.column, message: message.into() }
    }
    fn with_file(mut self, file: &Path) -> Self {
        self.file = Some(file.to_path_buf());
        self
    }
}

/// One `(:regions ...)` entry.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Region {
    /// `<target>_<name>`: the key BDDL atoms use (e.g. `kitchen_table_akita_black_bowl_init_region`).
    pub key: String,
    /// The name as written (e.g. `akita_black_bowl_init_region`, `top_region`).
    pub name: String,
    /// Workspace fixture (`main_table`, `kitchen_table`, ...) or an object/fixture instance name.
    pub target: String,
    /// Rectangles `(x_min, y_min, x_max, y_max)` relative to the workspace, metres.
    pub ranges: Vec<[f64; 4]>,
    /// Yaw interval in radians (LIBERO default `[0, 0]`).
    pub yaw_rotation: [f64; 2],
    /// Colour of the region site (LIBERO default `(0, 0, 1, 0)`, invisible).
    pub rgba: [f64; 4],
    pub pos: Pos,
}

/// A declared instance (`name - category`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Instance {
    pub name: String,
    /// Object category (LIBERO registry key such as `akita_black_bowl`), or `object`/`fixture` when untyped.
    pub category: String,
}

/// A predicate application such as `(on akita_black_bowl_1 plate_1)`. Names are lower-case.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Atom {
    pub predicate: String,
    pub args: Vec<String>,
    pub pos: Pos,
}

/// A goal expression. LIBERO itself only evaluates a conjunction of atoms; Or/Not are parsed so that other
/// consumers can use them (see [`Expr::conjunction_atoms`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub enum Expr {
    And(Vec<Expr>),
    Or(Vec<Expr>),
    Not(Box<Expr>),
    Atom(Atom),
}

impl Expr {
    /// The atoms of a pure conjunction (nested `and`s flattened, as bddl's `package_predicates` does), or `None`
    /// when the expression contains `or`/`not`.
    pub fn conjunction_atoms(&self) -> Option<Vec<&Atom>> {
        fn walk<'a>(e: &'a Expr, out: &mut Vec<&'a Atom>) -> bool {
            match e {
                Expr::Atom(a) => {
                    out.push(a);
                    true
                }
                Expr::And(items) => items.iter().all(|i| walk(i, out)),
                Expr::Or(_) | Expr::Not(_) => false,
            }
        }
        let mut out = Vec::new();
        walk(self, &mut out).then_some(out)
    }
}

/// A parsed LIBERO problem.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Problem {
    /// Lower-cased problem class, e.g. `libero_kitchen_tabletop_manipulation`.
    pub problem_name: String,
    pub domain: String,
    /// `:language` words joined by single spaces (lower-cased by the lexer).
    pub language: String,
    /// Regions in LIBERO dict order (keys unique; a repeated key keeps its first position, last value).
    pub regions: Vec<Region>,
    /// Fixtures in LIBERO dict order (categories by first appearance, instances in file order).
    pub fixtures: Vec<Instance>,
    /// Movable objects in LIBERO dict order.
    pub objects: Vec<Instance>,
    pub obj_of_interest: Vec<String>,
    /// `:init` atoms in file order.
    pub init: Vec<Atom>,
    /// `:goal` expression (`None` if the file has no goal section).
    pub goal: Option<Expr>,
    /// Section heads LIBERO does not know and ignores (e.g. a misspelt `:goals`).
    pub ignored_sections: Vec<String>,
}

impl Problem {
    /// Parse a BDDL file; errors name the file.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self, BddlError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|e| BddlError {
            file: Some(path.to_path_buf()),
            line: 0,
            column: 0,
            message: format!("cannot read: {e}"),
        })?;
        Self::parse(&text).map_err(|e| e.with_file(path))
    }

    /// Parse BDDL text.
    pub fn parse(text: &str) -> Result<Self, BddlError> {
        let root = sexpr::parse(text)?;
        parse_problem(&root)
    }

    pub fn region(&self, key: &str) -> Option<&Region> {
        self.regions.iter().find(|r| r.key == key)
    }

    /// The category of an object or fixture instance.
    pub fn category_of(&self, instance: &str) -> Option<&str> {
        self.objects.iter().chain(&self.fixtures).find(|i| i.name == instance).map(|i| i.category.as_str())
    }

    pub fn is_fixture(&self, instance: &str) -> bool {
        self.fixtures.iter().any(|i| i.name == instance)
    }

    pub fn is_object(&self, instance: &str) -> bool {
        self.objects.iter().any(|i| i.name == instance)
    }

    /// The goal as LIBERO evaluates it: a flat conjunction of atoms (empty if there is no goal).
    pub fn goal_atoms(&self) -> Option<Vec<&Atom>> {
        match &self.goal {
            None => Some(Vec::new()),
            Some(g) => g.conjunction_atoms(),
        }
    }
}

/// The task instruction LIBERO's benchmark shows to policies, derived from the file name
/// (`grab_language_from_filename`): for upper-case scene names drop up to and including `SCENEk_`; `_` → space.
pub fn language_from_filename(file_stem: &str) -> String {
    let stem = file_stem.strip_suffix(".bddl").unwrap_or(file_stem);
    let rest = if stem.chars().next().is_some_and(|c| c.is_ascii_uppercase()) {
        match stem.find("SCENE") {
            Some(i) => {
                let after = &stem[i + 5..];
                match after.find('_') {
                    Some(j) => &after[j + 1..],
                    None => after,
                }
            }
            None => stem,
        }
    } else {
        stem
    };
    rest.replace('_', " ")
}

fn expect_list<'a>(e: &'a SExpr, what: &str) -> Result<&'a [SExpr], BddlError> {
    match e {
        SExpr::List(items, _) => Ok(items),
        SExpr::Atom(s, pos) => Err(BddlError::at(*pos, format!("expected a parenthesised {what}, found `{s}`"))),
    }
}

fn expect_atom<'a>(e: &'a SExpr, what: &str) -> Result<&'a str, BddlError> {
    match e {
        SExpr::Atom(s, _) => Ok(s),
        SExpr::List(_, pos) => Err(BddlError::at(*pos, format!("expected {what}, found a list"))),
    }
}

fn parse_float(e: &SExpr, what: &str) -> Result<f64, BddlError> {
    let s = expect_atom(e, what)?;
    s.parse::<f64>().map_err(|_| BddlError::at(e.pos(), format!("{what}: `{s}` is not a number")))
}

/// `:yaw_rotation` values are Python expressions in LIBERO (`eval`); accept numbers and `[-]pi`, `[-]np.pi`,
/// optionally scaled as `k*pi`, `pi*k` or `pi/k`.
fn parse_angle(e: &SExpr) -> Result<f64, BddlError> {
    let s = expect_atom(e, "an angle")?;
    let err = || BddlError::at(e.pos(), format!("yaw angle `{s}` is neither a number nor a multiple of pi"));
    if let Ok(v) = s.parse::<f64>() {
        return Ok(v);
    }
    let (neg, body) = match s.strip_prefix('-') {
        Some(b) => (true, b),
        None => (false, s),
    };
    let is_pi = |t: &str| t == "pi" || t == "np.pi";
    let v = if is_pi(body) {
        std::f64::consts::PI
    } else if let Some((a, b)) = body.split_once('*') {
        match (is_pi(a), is_pi(b)) {
            (true, false) => std::f64::consts::PI * b.parse::<f64>().map_err(|_| err())?,
            (false, true) => a.parse::<f64>().map_err(|_| err())? * std::f64::consts::PI,
            _ => return Err(err()),
        }
    } else if let Some((a, b)) = body.split_once('/') {
        if !is_pi(a) {
            return Err(err());
        }
        std::f64::consts::PI / b.parse::<f64>().map_err(|_| err())?
    } else {
        return Err(err());
    };
    Ok(if neg { -v } else { v })
}

fn parse_region(item: &SExpr, regions: &mut Vec<Region>) -> Result<(), BddlError> {
    let parts = expect_list(item, "region")?;
    let Some(first) = parts.first() else {
        return Err(BddlError::at(item.pos(), "empty region"));
    };
    let name = expect_atom(first, "a region name")?.to_string();
    let mut target: Option<String> = None;
    let mut ranges = Vec::new();
    let mut yaw = [0.0, 0.0];
    let mut rgba = [0.0, 0.0, 1.0, 0.0];
    for attr in &parts[1..] {
        let a = expect_list(attr, "region attribute")?;
        let Some(head) = a.first() else {
            return Err(BddlError::at(attr.pos(), "empty region attribute"));
        };
        let head_s = expect_atom(head, "a region attribute name")?;
        match head_s {
            ":target" => {
                if a.len() != 2 {
                    return Err(BddlError::at(attr.pos(), "(:target NAME) takes exactly one name"));
                }
                target = Some(expect_atom(&a[1], "a target name")?.to_string());
            }
            ":ranges" => {
                if a.len() != 2 {
                    return Err(BddlError::at(attr.pos(), "(:ranges ((x0 y0 x1 y1) ...)) takes one list of rectangles"));
                }
                for rect in expect_list(&a[1], "list of rectangles")? {
                    let r = expect_list(rect, "rectangle (x_min y_min x_max y_max)")?;
                    if r.len() != 4 {
                        return Err(BddlError::at(
                            rect.pos(),
                            format!("a range rectangle needs 4 numbers (x_min y_min x_max y_max), found {}", r.len()),
                        ));
                    }
                    let mut v = [0.0; 4];
                    for (k, x) in r.iter().enumerate() {
                        v[k] = parse_float(x, "range bound")?;
                    }
                    ranges.push(v);
                }
            }
            ":yaw_rotation" => {
                if a.len() != 2 {
                    return Err(BddlError::at(attr.pos(), "(:yaw_rotation ((a b) ...)) takes one list of pairs"));
                }
                for pair in expect_list(&a[1], "list of yaw pairs")? {
                    let p = expect_list(pair, "yaw pair (a b)")?;
                    if p.len() != 2 {
                        return Err(BddlError::at(pair.pos(), format!("a yaw pair needs 2 angles, found {}", p.len())));
                    }
                    yaw = [parse_angle(&p[0])?, parse_angle(&p[1])?];
                }
            }
            ":rgba" => {
                let vals = if a.len() == 2 { expect_list(&a[1], "rgba list")? } else { &a[1..] };
                if vals.len() != 4 {
                    return Err(BddlError::at(attr.pos(), format!("(:rgba (r g b a)) needs 4 numbers, found {}", vals.len())));
                }
                for (k, x) in vals.iter().enumerate() {
                    rgba[k] = parse_float(x, "rgba component")?;
                }
            }
            other => {
                return Err(BddlError::at(head.pos(), format!("unknown region attribute `{other}` in region `{name}`")));
            }
        }
    }
    let Some(target) = target else {
        return Err(BddlError::at(item.pos(), format!("region `{name}` has no (:target NAME)")));
    };
    let key = format!("{target}_{name}");
    let region = Region { key: key.clone(), name, target, ranges, yaw_rotation: yaw, rgba, pos: item.pos() };
    // Python dict semantics: a repeated key keeps its first position and takes the new value.
    if let Some(existing) = regions.iter_mut().find(|r| r.key == key) {
        *existing = region;
    } else {
        regions.push(region);
    }
    Ok(())
}

/// `a b - type c - type2 d` → [(type, [a b]), (type2, [c]), (default, [d])] with dict semantics.
fn parse_typed_list(items: &[SExpr], default_type: &str, out: &mut Vec<(String, Vec<String>)>) -> Result<(), BddlError> {
    let mut pending: Vec<String> = Vec::new();
    let mut i = 0;
    while i < items.len() {
        let tok = expect_atom(&items[i], "a name")?;
        if tok == "-" {
            let Some(ty) = items.get(i + 1) else {
                return Err(BddlError::at(items[i].pos(), "`-` must be followed by a type name"));
            };
            let ty = expect_atom(ty, "a type name")?.to_string();
            let names = std::mem::take(&mut pending);
            if let Some(slot) = out.iter_mut().find(|(t, _)| *t == ty) {
                slot.1 = names; // Python: objects[TYPE] = list (assignment, keeps key position)
            } else {
                out.push((ty, names));
            }
            i += 2;
        } else {
            pending.push(tok.to_string());
            i += 1;
        }
    }
    if !pending.is_empty() {
        if let Some(slot) = out.iter_mut().find(|(t, _)| t == default_type) {
            slot.1.extend(pending);
        } else {
            out.push((default_type.to_string(), pending));
        }
    }
    Ok(())
}

fn parse_atom(e: &SExpr) -> Result<Atom, BddlError> {
    let items = expect_list(e, "predicate")?;
    let Some(head) = items.first() else {
        return Err(BddlError::at(e.pos(), "empty predicate"));
    };
    let predicate = expect_atom(head, "a predicate name")?.to_string();
    let mut args = Vec::with_capacity(items.len() - 1);
    for a in &items[1..] {
        args.push(expect_atom(a, "a predicate argument")?.to_string());
    }
    Ok(Atom { predicate, args, pos: e.pos() })
}

fn parse_expr(e: &SExpr) -> Result<Expr, BddlError> {
    let items = expect_list(e, "goal expression")?;
    let Some(head) = items.first() else {
        return Err(BddlError::at(e.pos(), "empty goal expression"));
    };
    match expect_atom(head, "an operator or predicate")? {
        "and" => Ok(Expr::And(items[1..].iter().map(parse_expr).collect::<Result<_, _>>()?)),
        "or" => Ok(Expr::Or(items[1..].iter().map(parse_expr).collect::<Result<_, _>>()?)),
        "not" => {
            if items.len() != 2 {
                return Err(BddlError::at(e.pos(), "(not X) takes exactly one expression"));
            }
            Ok(Expr::Not(Box::new(parse_expr(&items[1])?)))
        }
        _ => Ok(Expr::Atom(parse_atom(e)?)),
    }
}

fn parse_problem(root: &SExpr) -> Result<Problem, BddlError> {
    let items = expect_list(root, "(define ...)")?;
    match items.first() {
        Some(SExpr::Atom(s, _)) if s == "define" => {}
        Some(other) => return Err(BddlError::at(other.pos(), "a BDDL problem must start with `(define`")),
        None => return Err(BddlError::at(root.pos(), "empty BDDL file")),
    }
    let mut problem_name: Option<String> = None;
    let mut domain: Option<String> = None;
    let mut language = String::new();
    let mut regions = Vec::new();
    let mut fixtures: Vec<(String, Vec<String>)> = Vec::new();
    let mut objects: Vec<(String, Vec<String>)> = Vec::new();
    let mut obj_of_interest = Vec::new();
    let mut init = Vec::new();
    let mut goal = None;
    let mut ignored_sections = Vec::new();
    // LIBERO pops sections from the end.
    for group in items[1..].iter().rev() {
        let g = expect_list(group, "section")?;
        let Some(head) = g.first() else {
            return Err(BddlError::at(group.pos(), "empty section"));
        };
        let head_s = expect_atom(head, "a section name")?;
        match head_s {
            "problem" => {
                let Some(last) = g.last().filter(|_| g.len() >= 2) else {
                    return Err(BddlError::at(group.pos(), "(problem NAME) needs a name"));
                };
                problem_name = Some(expect_atom(last, "a problem name")?.to_string());
            }
            ":domain" => {
                let d = g.last().map(|x| expect_atom(x, "a domain name")).transpose()?.unwrap_or("");
                if d != "robosuite" {
                    return Err(BddlError::at(group.pos(), format!("domain must be `robosuite`, found `{d}`")));
                }
                domain = Some(d.to_string());
            }
            ":requirements" => {}
            ":objects" => parse_typed_list(&g[1..], "object", &mut objects)?,
            ":fixtures" => parse_typed_list(&g[1..], "fixture", &mut fixtures)?,
            ":obj_of_interest" => {
                for a in &g[1..] {
                    obj_of_interest.push(expect_atom(a, "an object name")?.to_string());
                }
            }
            ":regions" => {
                for r in &g[1..] {
                    parse_region(r, &mut regions)?;
                }
            }
            ":language" => {
                let mut words = Vec::new();
                for a in &g[1..] {
                    words.push(expect_atom(a, "a word")?);
                }
                language = words.join(" ");
            }
            ":init" => {
                init = g[1..].iter().map(parse_atom).collect::<Result<_, _>>()?;
            }
            ":goal" => {
                let Some(body) = g.get(1) else {
                    return Err(BddlError::at(group.pos(), "(:goal EXPR) needs an expression"));
                };
                goal = Some(parse_expr(body)?);
            }
            // LIBERO's own :scene_properties handler is broken (NameError); no stock file uses it.
            ":scene_properties" => {
                return Err(BddlError::at(head.pos(), "`:scene_properties` is not supported (LIBERO cannot load it either)"));
            }
            // LIBERO prints and ignores unknown sections; keep them visible to callers.
            other => ignored_sections.push(other.to_string()),
        }
    }
    let Some(problem_name) = problem_name else {
        return Err(BddlError::at(root.pos(), "missing (problem NAME)"));
    };
    let flatten = |groups: Vec<(String, Vec<String>)>| -> Vec<Instance> {
        groups
            .into_iter()
            .flat_map(|(cat, names)| names.into_iter().map(move |name| Instance { name, category: cat.clone() }))
            .collect()
    };
    Ok(Problem {
        problem_name,
        domain: domain.unwrap_or_else(|| "robosuite".into()),
        language,
        regions,
        fixtures: flatten(fixtures),
        objects: flatten(objects),
        obj_of_interest,
        init,
        goal,
        ignored_sections,
    })
}

#[cfg(test)]
mod tests;

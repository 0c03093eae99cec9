//! One syntax for naming a set of tasks, shared by every command and page that takes one: `run --tasks`,
//! `expert --tasks`, `tasks list --tasks`, `serve --thumbnails-ahead`, `bench scale --tasks` and the Tasks page's
//! `/tasks?tasks=…` (docs/commands.md, "Selecting tasks").
//!
//! A selection is a comma-separated list of terms; it selects their union, in the order written, each task once:
//!
//! | term | selects |
//! |---|---|
//! | `all` | every registered pool entry (every release task is one of them, as its pool twin) |
//! | `release` | the 30 release tasks T01–T30 |
//! | `stock` | the entries of the five stock LIBERO suites |
//! | `SUITE` or `suite:SUITE` | the entries of a registered suite (`libero_90`, `robomemarena`, …) |
//! | `group:G` | the entries of a group (`perception`, `short_horizon`, `long_horizon`) |
//! | `T11` (or `t11`, `11`) | one release task |
//! | `SUITE/ID` or `SUITE/NAME` | one pool entry (`libero_90/35`, `libero_90/KITCHEN_SCENE3_turn_on_the_stove`) |
//! | `match:TEXT` | every release task and entry whose id, name or reference contains TEXT (any case) |
//!
//! A term that names one task is [`Pick::named`]: a command refuses it when it cannot serve that task (with the
//! reason), while the members of a set it cannot serve are left out and reported.
use std::fmt;
use std::str::FromStr;

use crate::catalog::TaskEntry;
use crate::pool::{GROUPS, Pool, PoolEntry, REGISTERED_SUITES};

/// Bounds on a selection from outside (a query string, an environment variable).
const MAX_SELECTION_BYTES: usize = 4096;
const MAX_TERMS: usize = 256;

/// Why a selection cannot be read or resolved; says what would be accepted.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SelectionError {
    #[error("empty task selection: name `all`, `release`, `stock`, a suite, `group:G`, a task (`T11`, `libero_90/35`) or `match:TEXT`")]
    Empty,
    #[error("task selection too long: at most {MAX_TERMS} terms and {MAX_SELECTION_BYTES} bytes")]
    TooLong,
    #[error("no pool suite {0:?}: a selection term is all, release, stock, a suite ({suites}), group:G, a task (T11, suite/id, suite/name) or match:TEXT", suites = suite_names())]
    NoSuite(String),
    #[error("no group {0:?}: groups are {groups}", groups = GROUPS.join(", "))]
    NoGroup(String),
    #[error("`match:` needs some text to look for")]
    EmptyMatch,
    #[error("no release task {0:?}: release tasks are T01–T30")]
    NoReleaseTask(String),
    #[error("{0}")]
    NoEntry(String),
    #[error("{0:?} is not a task selection term: expected all, release, stock, a suite, suite:S, group:G, T11, suite/id, suite/name or match:TEXT")]
    Unknown(String),
    #[error("`match:{0}` matches no task")]
    NoMatch(String),
    /// A task named on its own that does not run here, with the reason.
    #[error("{0}")]
    DoesNotRun(String),
}

fn suite_names() -> String {
    REGISTERED_SUITES.map(|(s, _)| s).join(", ")
}

/// One term of a selection.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Term {
    All,
    Release,
    Stock,
    Suite(String),
    Group(String),
    /// A release task by number.
    ReleaseTask(u32),
    /// A pool entry as written (`suite/id` or `suite/name`), resolved against the pool.
    Entry(String),
    /// Lower-cased text to look for.
    Match(String),
}

impl Term {
    /// Whether the term names one task rather than a set.
    pub fn is_single(&self) -> bool {
        matches!(self, Term::ReleaseTask(_) | Term::Entry(_))
    }
}

impl fmt::Display for Term {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Term::All => f.write_str("all"),
            Term::Release => f.write_str("release"),
            Term::Stock => f.write_str("stock"),
            Term::Suite(s) => f.write_str(s),
            Term::Group(g) => write!(f, "group:{g}"),
            Term::ReleaseTask(n) => write!(f, "T{n:02}"),
            Term::Entry(e) => f.write_str(e),
            Term::Match(t) => write!(f, "match:{t}"),
        }
    }
}

impl FromStr for Term {
    type Err = SelectionError;
    fn from_str(raw: &str) -> Result<Self, Self::Err> {
        let t = raw.trim();
        let registered = |s: &str| REGISTERED_SUITES.iter().any(|(r, _)| *r == s);
        let suite = |s: &str| match s {
            "all" => Ok(Term::All),
            "release" => Ok(Term::Release),
            "stock" => Ok(Term::Stock),
            s if registered(s) => Ok(Term::Suite(s.to_owned())),
            s => Err(SelectionError::NoSuite(s.to_owned())),
        };
        if let Some(s) = t.strip_prefix("suite:") {
            return suite(s.trim());
        }
        if let Some(g) = t.strip_prefix("group:") {
            let g = g.trim();
            return if GROUPS.contains(&g) { Ok(Term::Group(g.to_owned())) } else { Err(SelectionError::NoGroup(g.to_owned())) };
        }
        if let Some(text) = t.strip_prefix("match:") {
            let text = text.trim();
            return if text.is_empty() { Err(SelectionError::EmptyMatch) } else { Ok(Term::Match(text.to_lowercase())) };
        }
        if let Some((s, rest)) = t.split_once('/') {
            if !registered(s) {
                return Err(SelectionError::NoSuite(s.to_owned()));
            }
            if rest.trim().is_empty() {
                return Err(SelectionError::Unknown(t.to_owned()));
            }
            return Ok(Term::Entry(t.to_owned()));
        }
        let digits = t.strip_prefix(['T', 't']).unwrap_or(t);
        if !digits.is_empty()
            && digits.bytes().all(|b| b.is_ascii_digit())
        {
            return match digits.parse::<u32>() {
                Ok(n) if (1..=30).contains(&n) => Ok(Term::ReleaseTask(n)),
                _ => Err(SelectionError::NoReleaseTask(t.to_owned())),
            };
        }
        suite(t)
    }
}

/// A parsed selection: its terms in order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Selection {
    terms: Vec<Term>,
}

impl Selection {
    /// Every registered entry (`all`).
    pub fn all() -> Self {
        Self { terms: vec![Term::All] }
    }

    /// Reads several values (a repeated flag), each comma-separated, as one selection.
    pub fn from_parts<S: AsRef<str>>(parts: &[S]) -> Result<Self, SelectionError> {
        let joined = parts.iter().map(AsRef::as_ref).collect::<Vec<_>>().join(",");
        joined.parse()
    }

    pub fn terms(&self) -> &[Term] {
        &self.terms
    }

    /// The selection with `term` first, unless it names it already (then unchanged).
    pub fn with_first(&self, term: Term) -> Self {
        if self.terms.contains(&term) {
            return self.clone();
        }
        Self { terms: std::iter::once(term).chain(self.terms.iter().cloned()).collect() }
    }

    /// The tasks selected, in the order the terms name them, each once (a task named on its own and inside a set
    /// keeps the place it is first named at, and counts as named).
    pub fn resolve<'a>(&self, release: &'a [TaskEntry], pool: &'a Pool) -> Result<Vec<Pick<'a>>, SelectionError> {
        let mut picks: Vec<Pick<'a>> = Vec::new();
        let mut add = |member: Member<'a>, named: bool| match picks.iter_mut().find(|p| p.member.same(&member)) {
            Some(p) => p.named |= named,
            None => picks.push(Pick { member, named }),
        };
        let entries = pool.entries();
        for term in &self.terms {
            match term {
                Term::All => entries.iter().for_each(|e| add(Member::Entry(e), false)),
                Term::Release => release.iter().for_each(|t| add(Member::Release(t), false)),
                Term::Stock => entries.iter().filter(|e| e.is_stock()).for_each(|e| add(Member::Entry(e), false)),
                Term::Suite(s) => entries.iter().filter(|e| &e.suite == s).for_each(|e| add(Member::Entry(e), false)),
                Term::Group(g) => entries.iter().filter(|e| &e.group == g).for_each(|e| add(Member::Entry(e), false)),
                Term::ReleaseTask(n) => {
                    let t = release.iter().find(|t| t.number == *n).ok_or_else(|| SelectionError::NoReleaseTask(term.to_string()))?;
                    add(Member::Release(t), true);
                }
                Term::Entry(id) => add(Member::Entry(pool.lookup(id).map_err(SelectionError::NoEntry)?), true),
                Term::Match(text) => {
                    let hit = |s: &str| s.to_lowercase().contains(text.as_str());
                    let found: Vec<Member<'a>> = release
                        .iter()
                        .filter(|t| hit(&t.id) || hit(&t.name))
                        .map(Member::Release)
                        .chain(entries.iter().filter(|e| hit(&e.id()) || hit(&e.reference())).map(Member::Entry))
                        .collect();
                    if found.is_empty() {
                        return Err(SelectionError::NoMatch(text.clone()));
                    }
                    found.into_iter().for_each(|m| add(m, false));
                }
            }
        }
        Ok(picks)
    }

    /// The selected tasks that run in this build: a set's members that do not are left out, a task named on its own
    /// that does not is refused with the reason.
    pub fn runnable<'a>(&self, release: &'a [TaskEntry], pool: &'a Pool) -> Result<Vec<Pick<'a>>, SelectionError> {
        let mut out = Vec::new();
        for pick in self.resolve(release, pool)? {
            match pick.member.why_not() {
                None => out.push(pick),
                Some(why) if pick.named => return Err(SelectionError::DoesNotRun(format!("{} is {why}", pick.member.id()))),
                Some(_) => {}
            }
        }
        Ok(out)
    }
}

impl FromStr for Selection {
    type Err = SelectionError;
    fn from_str(text: &str) -> Result<Self, Self::Err> {
        if text.len() > MAX_SELECTION_BYTES {
            return Err(SelectionError::TooLong);
        }
        let parts: Vec<&str> = text.split(',').map(str::trim).filter(|p| !p.is_empty()).collect();
        if parts.is_empty() {
            return Err(SelectionError::Empty);
        }
        if parts.len() > MAX_TERMS {
            return Err(SelectionError::TooLong);
        }
        let mut terms: Vec<Term> = Vec::with_capacity(parts.len());
        for p in parts {
            let term: Term = p.parse()?;
            if !terms.contains(&term) {
                terms.push(term);
            }
        }
        Ok(Self { terms })
    }
}

impl fmt::Display for Selection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let text: Vec<String> = self.terms.iter().map(Term::to_string).collect();
        f.write_str(&text.join(","))
    }
}

/// A selected task: a release task or a pool entry.
#[derive(Debug, Clone, Copy)]
pub enum Member<'a> {
    Release(&'a TaskEntry),
    Entry(&'a PoolEntry),
}

impl Member<'_> {
    /// `T11` or `suite/task_id`.
    pub fn id(&self) -> String {
        match self {
            Member::Release(t) => t.id.clone(),
            Member::Entry(e) => e.id(),
        }
    }

    /// Why the task does not run in this build; `None` when it runs.
    pub fn why_not(&self) -> Option<String> {
        match self {
            Member::Release(t) => (!t.implemented)
                .then(|| format!("not implemented in this build: {}", t.not_implemented_reason.as_deref().unwrap_or("no reason given"))),
            Member::Entry(e) => e.why_not(),
        }
    }

    fn same(&self, other: &Member<'_>) -> bool {
        match (self, other) {
            (Member::Release(a), Member::Release(b)) => a.number == b.number,
            (Member::Entry(a), Member::Entry(b)) => a.suite == b.suite && a.task_id == b.task_id,
            _ => false,
        }
    }
}

/// One selected task and whether a term named it on its own.
#[derive(Debug, Clone, Copy)]
pub struct Pick<'a> {
    pub member: Member<'a>,
    pub named: bool,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Catalog;

    fn ids(sel: &str) -> Vec<String> {
        let catalog = Catalog::discover().unwrap();
        let pool = Pool::discover().unwrap();
        let s: Selection = sel.parse().unwrap();
        s.resolve(catalog.tasks(), &pool).unwrap().iter().map(|p| p.member.id()).collect()
    }

    #[test]
    fn terms_union_in_order_each_task_once() {
        let got = ids("T11, libero_object, libero_object/3 ,libero_90/35,t11");
        assert_eq!(got.len(), 12, "T11, 10 libero_object entries and libero_90/35: {got:?}");
        assert_eq!(got[0], "T11");
        assert_eq!(got[1], "libero_object/0");
        assert_eq!(got.last().map(String::as_str), Some("libero_90/35"));
        assert_eq!(ids("suite:libero_object"), ids("libero_object"), "`suite:` is optional");
    }

    #[test]
    fn sets_cover_the_pool_and_the_release_tasks() {
        let pool = Pool::discover().unwrap();
        assert_eq!(ids("all").len(), pool.entries().len());
        assert_eq!(ids("release").len(), 30);
        assert_eq!(ids("stock").len(), 130);
        let long = ids("group:long_horizon");
        assert!(!long.is_empty() && long.len() == pool.select("all", Some("long_horizon")).count());
        assert_eq!(ids("libero_90/KITCHEN_SCENE3_turn_on_the_stove").len(), 1, "an entry by name");
    }

    #[test]
    fn match_finds_ids_and_names_in_any_case() {
        let got = ids("match:kitchen_scene3");
        assert!(!got.is_empty() && got.iter().all(|id| id.starts_with("libero_")), "{got:?}");
        let catalog = Catalog::discover().unwrap();
        let pool = Pool::discover().unwrap();
        let none: Selection = "match:no_such_task_anywhere".parse().unwrap();
        assert_eq!(none.resolve(catalog.tasks(), &pool).unwrap_err(), SelectionError::NoMatch("no_such_task_anywhere".into()));
    }

    #[test]
    fn named_tasks_are_marked_named_and_sets_are_not() {
        let catalog = Catalog::discover().unwrap();
        let pool = Pool::discover().unwrap();
        let s: Selection = "libero_object,libero_object/3".parse().unwrap();
        let picks = s.resolve(catalog.tasks(), &pool).unwrap();
        assert_eq!(picks.iter().filter(|p| p.named).map(|p| p.member.id()).collect::<Vec<_>>(), ["libero_object/3"]);
    }

    #[test]
    fn bad_terms_are_refused_saying_what_is_accepted() {
        let catalog = Catalog::discover().unwrap();
        let pool = Pool::discover().unwrap();
        for (bad, want) in [
            ("", "empty task selection"),
            (" , ", "empty task selection"),
            ("suite:nope", "no pool suite \"nope\""),
            ("nope/3", "no pool suite \"nope\""),
            ("group:medium", "no group \"medium\""),
            ("T31", "no release task"),
            ("T0", "no release task"),
            ("match:", "needs some text"),
            ("libero_100", "no pool suite \"libero_100\""),
            ("kitchen", "a selection term is all, release"),
            ("libero_90/", "not a task selection term"),
        ] {
            let err = bad.parse::<Selection>().unwrap_err().to_string();
            assert!(err.contains(want), "{bad:?}: {err}");
        }
        let err = "libero_90/999".parse::<Selection>().unwrap().resolve(catalog.tasks(), &pool).unwrap_err().to_string();
        assert!(err.contains("no pool entry"), "{err}");
        let long = vec!["T11"; MAX_TERMS + 1].join(",");
        assert_eq!(long.parse::<Selection>().unwrap_err(), SelectionError::TooLong);
    }

    #[test]
    fn a_selection_prints_as_it_parses() {
        let s: Selection = "suite:libero_10, t07,group:perception,match:Stove".parse().unwrap();
        assert_eq!(s.to_string(), "libero_10,T07,group:perception,match:stove");
        assert_eq!(s.to_string().parse::<Selection>().unwrap(), s);
    }

    #[test]
    fn a_term_put_first_is_added_once_even_to_the_longest_selection() {
        let s: Selection = "all,T14".parse().unwrap();
        assert_eq!(s.with_first(Term::Release).to_string(), "release,all,T14");
        let r: Selection = "T14,release".parse().unwrap();
        assert_eq!(r.with_first(Term::Release), r, "named already: unchanged");
        let longest: Selection = (1..=MAX_TERMS).map(|n| format!("libero_90/{n}")).collect::<Vec<_>>().join(",").parse().unwrap();
        assert_eq!(longest.with_first(Term::Release).terms().len(), MAX_TERMS + 1, "not parsed again, so not refused as too long");
    }
}

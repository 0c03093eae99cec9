//! bddl 1.0.1 `scan_tokens`: strip `;` comments, lower-case, tokens = `(`, `)` or runs of other non-space
//! characters; exactly one top-level list. Positions are kept for error messages.
use crate::BddlError;

/// 1-based line/column in the source text.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct Pos {
    pub line: usize,
    pub column: usize,
}

/// A token or a parenthesised list of them.
#[derive(Debug, Clone, PartialEq)]
pub enum SExpr {
    Atom(String, Pos),
    List(Vec<SExpr>, Pos),
}

impl SExpr {
    pub fn pos(&self) -> Pos {
        match self {
            SExpr::Atom(_, p) | SExpr::List(_, p) => *p,
        }
    }
}

/// Parse the whole text into its single top-level list.
pub fn parse(text: &str) -> Result<SExpr, BddlError> {
    let mut stack: Vec<(Vec<SExpr>, Pos)> = Vec::new();
    let mut top: Vec<SExpr> = Vec::new();
    let mut line = 1usize;
    for raw_line in text.split('\n') {
        let content = match raw_line.find(';') {
            Some(i) => &raw_line[..i],
            None => raw_line,
        };
        let lower = content.to_lowercase();
        let chars: Vec<(usize, char)> = lower.char_indices().collect();
        let mut k = 0;
        while k < chars.len() {
            let (_, c) = chars[k];
            let pos = Pos { line, column: k + 1 };
            if c == '(' {
                stack.push((Vec::new(), pos));
                k += 1;
            } else if c == ')' {
                let Some((items, open)) = stack.pop() else {
                    return Err(BddlError::at(pos, "unbalanced `)`: no matching `(`"));
                };
                let list = SExpr::List(items, open);
                match stack.last_mut() {
                    Some((parent, _)) => parent.push(list),
                    None => top.push(list),
                }
                k += 1;
            } else if c.is_whitespace() {
                k += 1;
            } else {
                let start = k;
                while k < chars.len() && !chars[k].1.is_whitespace() && chars[k].1 != '(' && chars[k].1 != ')' {
                    k += 1;
                }
                let tok: String = chars[start..k].iter().map(|(_, c)| *c).collect();
                let atom = SExpr::Atom(tok, pos);
                match stack.last_mut() {
                    Some((parent, _)) => parent.push(atom),
                    None => {
                        return Err(BddlError::at(pos, format!("token `{}` outside of the top-level list", atom_text(&atom))));
                    }
                }
            }
        }
        line += 1;
    }
    if let Some((_, open)) = stack.last() {
        return Err(BddlError::at(*open, "missing `)`: this `(` is never closed"));
    }
    match top.len() {
        0 => Err(BddlError::at(Pos::default(), "empty file: expected `(define ...)`")),
        1 => Ok(top.pop().expect("len checked")),
        _ => Err(BddlError::at(top[1].pos(), "malformed expression: more than one top-level list")),
    }
}

fn atom_text(e: &SExpr) -> &str {
    match e {
        SExpr::Atom(s, _) => s,
        SExpr::List(..) => "(...)",
    }
}

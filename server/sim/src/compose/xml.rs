//! A small mutable XML tree with ElementTree semantics (ordered attributes and children, no comments), used to
//! replay robosuite's MJCF edits step by step, plus Python-compatible number formatting.
use std::path::Path;

use crate::SimError;

/// One XML element; attribute order is kept (ElementTree keeps insertion order).
#[derive(Debug, Clone, PartialEq)]
pub struct Element {
    pub tag: String,
    pub attrs: Vec<(String, String)>,
    pub children: Vec<Element>,
}

impl Element {
    pub fn new(tag: &str) -> Self {
        Self { tag: tag.to_string(), attrs: Vec::new(), children: Vec::new() }
    }

    /// `ET.Element(tag, attrib)` with attributes in the given order.
    pub fn with_attrs(tag: &str, attrs: &[(&str, String)]) -> Self {
        let mut e = Self::new(tag);
        for (k, v) in attrs {
            e.set(k, v.clone());
        }
        e
    }

    pub fn get(&self, key: &str) -> Option<&str> {
        self.attrs.iter().find(|(k, _)| k == key).map(|(_, v)| v.as_str())
    }

    /// `Element.set`: replaces in place or appends.
    pub fn set(&mut self, key: &str, value: impl Into<String>) {
        let value = value.into();
        match self.attrs.iter_mut().find(|(k, _)| k == key) {
            Some(slot) => slot.1 = value,
            None => self.attrs.push((key.to_string(), value)),
        }
    }

    pub fn remove_attr(&mut self, key: &str) -> Option<String> {
        let i = self.attrs.iter().position(|(k, _)| k == key)?;
        Some(self.attrs.remove(i).1)
    }

    /// First direct child with this tag (`root.find(tag)`).
    pub fn child(&self, tag: &str) -> Option<&Element> {
        self.children.iter().find(|c| c.tag == tag)
    }

    pub fn child_mut(&mut self, tag: &str) -> Option<&mut Element> {
        self.children.iter_mut().find(|c| c.tag == tag)
    }

    /// First direct child with this tag and `name` (`find("./tag[@name='x']")`).
    pub fn child_named_mut(&mut self, tag: &str, name: &str) -> Option<&mut Element> {
        self.children.iter_mut().find(|c| c.tag == tag && c.get("name") == Some(name))
    }

    pub fn child_named(&self, tag: &str, name: &str) -> Option<&Element> {
        self.children.iter().find(|c| c.tag == tag && c.get("name") == Some(name))
    }

    /// Depth-first (pre-order) search for an element with this tag and name (robosuite `find_elements`).
    pub fn find_named_mut(&mut self, tag: &str, name: &str) -> Option<&mut Element> {
        if self.tag == tag && self.get("name") == Some(name) {
            return Some(self);
        }
        for c in &mut self.children {
            if let Some(found) = c.find_named_mut(tag, name) {
                return Some(found);
            }
        }
        None
    }

    pub fn find_named(&self, tag: &str, name: &str) -> Option<&Element> {
        if self.tag == tag && self.get("name") == Some(name) {
            return Some(self);
        }
        self.children.iter().find_map(|c| c.find_named(tag, name))
    }

    /// Visit every element in pre-order with its parent's tag.
    pub fn walk<'a>(&'a self, parent: Option<&'a Element>, f: &mut dyn FnMut(&'a Element, Option<&'a Element>)) {
        f(self, parent);
        for c in &self.children {
            c.walk(Some(self), f);
        }
    }

    /// Mutable pre-order visit; the closure gets the parent's tag.
    pub fn walk_mut(&mut self, parent_tag: Option<&str>, f: &mut dyn FnMut(&mut Element, Option<&str>)) {
        f(self, parent_tag);
        let tag = self.tag.clone();
        for c in &mut self.children {
            c.walk_mut(Some(&tag), f);
        }
    }

    /// Serialise like `ET.tostring` (attribute order kept, self-closing empty elements).
    pub fn to_xml(&self) -> String {
        let mut out = String::with_capacity(1 << 16);
        self.write(&mut out, 0);
        out
    }

    fn write(&self, out: &mut String, depth: usize) {
        for _ in 0..depth {
            out.push_str("  ");
        }
        out.push('<');
        out.push_str(&self.tag);
        for (k, v) in &self.attrs {
            out.push(' ');
            out.push_str(k);
            out.push_str("=\"");
            escape_into(v, out);
            out.push('"');
        }
        if self.children.is_empty() {
            out.push_str(" />\n");
        } else {
            out.push_str(">\n");
            for c in &self.children {
                c.write(out, depth + 1);
            }
            for _ in 0..depth {
                out.push_str("  ");
            }
            out.push_str("</");
            out.push_str(&self.tag);
            out.push_str(">\n");
        }
    }
}

fn escape_into(v: &str, out: &mut String) {
    for c in v.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\n' => out.push_str("&#10;"),
            _ => out.push(c),
        }
    }
}

fn convert(node: roxmltree::Node) -> Element {
    let mut e = Element::new(node.tag_name().name());
    for a in node.attributes() {
        e.attrs.push((a.name().to_string(), a.value().to_string()));
    }
    for c in node.children().filter(|c| c.is_element()) {
        e.children.push(convert(c));
    }
    e
}

/// Parse an XML file into an [`Element`] tree (comments and text dropped, as MJCF ignores them).
pub fn parse_file(path: &Path) -> Result<Element, SimError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| SimError::Assets(format!("cannot read {}: {e}", path.display())))?;
    parse_str(&text).map_err(|e| SimError::Assets(format!("{}: {e}", path.display())))
}

pub fn parse_str(text: &str) -> Result<Element, SimError> {
    let doc = roxmltree::Document::parse(text).map_err(|e| SimError::Input(format!("XML: {e}")))?;
    Ok(convert(doc.root_element()))
}

/// Python `repr(float)` (shortest round-trip digits; exponent form below 1e-4 and from 1e16 on).
pub fn py_float(x: f64) -> String {
    if x.is_nan() {
        return "nan".into();
    }
    if x.is_infinite() {
        return if x > 0.0 { "inf".into() } else { "-inf".into() };
    }
    if x == 0.0 {
        return if x.is_sign_negative() { "-0.0".into() } else { "0.0".into() };
    }
    let sci = format!("{x:e}"); // shortest digits, e.g. "1.5e-5", "-2e16"
    let (mant, exp) = sci.split_once('e').expect("`{:e}` always has an exponent");
    let exp: i32 = exp.parse().expect("exponent is an integer");
    if (-4..16).contains(&exp) {
        let s = format!("{x}");
        if s.contains('.') { s } else { format!("{s}.0") }
    } else {
        let sign = if exp < 0 { "-" } else { "+" };
        format!("{mant}e{sign}{:02}", exp.abs())
    }
}

/// robosuite `array_to_string` of float values.
pub fn array_to_string(v: &[f64]) -> String {
    v.iter().map(|x| py_float(*x)).collect::<Vec<_>>().join(" ")
}

/// robosuite `string_to_array` (`float(x) for x in s.strip().split(" ")`).
pub fn string_to_array(s: &str) -> Result<Vec<f64>, SimError> {
    s.trim()
        .split(' ')
        .map(|t| t.parse::<f64>().map_err(|_| SimError::Input(format!("`{s}` is not a list of numbers"))))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn py_float_matches_python_repr() {
        assert_eq!(py_float(0.9), "0.9");
        assert_eq!(py_float(1.0), "1.0");
        assert_eq!(py_float(-0.66), "-0.66");
        assert_eq!(py_float(2e-5), "2e-05");
        assert_eq!(py_float(0.0001), "0.0001");
        assert_eq!(py_float(6.123233995736766e-17), "6.123233995736766e-17");
        assert_eq!(py_float(1e16), "1e+16");
        assert_eq!(py_float(1.6103500240372423), "1.6103500240372424");
        assert_eq!(py_float(-0.0), "-0.0");
    }
}

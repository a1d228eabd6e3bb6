//! Field paths from byte offsets and byte offsets from field paths, through the spans that
//! toml's own parser (`toml_edit`) records for every key and value.

use std::ops::Range;
use toml_edit::{ArrayOfTables, ImDocument, InlineTable, Item, Table, Value};

/// 1-based line and column (in characters) of a byte offset of `text`.
#[must_use]
pub fn line_column(text: &str, offset: usize) -> (usize, usize) {
    let mut offset = offset.min(text.len());
    while !text.is_char_boundary(offset) {
        offset -= 1;
    }
    let before = text.get(..offset).unwrap_or("");
    let line = before.matches('\n').count() + 1;
    let column = before.rsplit('\n').next().map_or(0, |s| s.chars().count()) + 1;
    (line, column)
}

/// One step of a field path.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Segment {
    Key(String),
    Index(usize),
}

fn render(path: &[Segment]) -> String {
    let mut out = String::new();
    for seg in path {
        match seg {
            Segment::Key(k) => {
                if !out.is_empty() {
                    out.push('.');
                }
                out.push_str(k);
            }
            Segment::Index(i) => {
                out.push('[');
                out.push_str(&i.to_string());
                out.push(']');
            }
        }
    }
    out
}

/// `a.b[2].c` → segments. Returns `None` for a malformed path.
fn parse_path(path: &str) -> Option<Vec<Segment>> {
    let mut out = Vec::new();
    for part in path.split('.') {
        let (key, mut rest) = match part.find('[') {
            Some(at) => (part.get(..at)?, part.get(at..)?),
            None => (part, ""),
        };
        if !key.is_empty() {
            out.push(Segment::Key(key.to_owned()));
        }
        while let Some(stripped) = rest.strip_prefix('[') {
            let close = stripped.find(']')?;
            out.push(Segment::Index(stripped.get(..close)?.parse().ok()?));
            rest = stripped.get(close + 1..)?;
        }
        if !rest.is_empty() {
            return None;
        }
    }
    Some(out)
}

fn contains(span: Option<Range<usize>>, offset: usize) -> bool {
    span.is_some_and(|s| s.start <= offset && (offset < s.end || s.start == s.end))
}

/// A parsed TOML document with the spans of its keys and values.
pub struct TomlLocator<'a> {
    text: &'a str,
    doc: Option<ImDocument<&'a str>>,
}

impl<'a> TomlLocator<'a> {
    /// Parses `text` (a text that does not parse locates nothing).
    #[must_use]
    pub fn new(text: &'a str) -> Self {
        Self {
            text,
            doc: ImDocument::parse(text).ok(),
        }
    }

    /// The dotted path (`a.b[2].c`) of the innermost key or value at a byte offset.
    #[must_use]
    pub fn field_at(&self, offset: usize) -> Option<String> {
        let doc = self.doc.as_ref()?;
        let mut best: Option<Vec<Segment>> = None;
        walk_table(doc.as_table(), &mut Vec::new(), offset, &mut best);
        best.map(|p| render(&p))
    }

    /// The field a parse error is about: the path at its span, completed by the name a
    /// "missing field `x`" or "unknown field `x`" message quotes when the span is the
    /// enclosing table.
    #[must_use]
    pub fn field_for_error(&self, span: Range<usize>, message: &str) -> Option<String> {
        let at = self.field_at(span.start);
        let quoted = super::quoted_name(message)
            .filter(|_| message.contains("missing field") || message.contains("unknown field"));
        match (at, quoted) {
            (Some(at), Some(name)) if !at.ends_with(&name) => Some(format!("{at}.{name}")),
            (None, Some(name)) => Some(name),
            (at, _) => at,
        }
    }

    /// The 1-based line where a dotted field path is written; for a field that is not written
    /// (a default, a missing field), the line of the deepest table of the path that is.
    #[must_use]
    pub fn line_of(&self, path: &str) -> Option<usize> {
        self.lookup(path).map(|(line, _)| line)
    }

    /// The 1-based line of a dotted field path only when the field itself is written.
    #[must_use]
    pub fn exact_line_of(&self, path: &str) -> Option<usize> {
        self.lookup(path)
            .and_then(|(line, exact)| exact.then_some(line))
    }

    /// The line of the deepest written step of `path`, and whether that is the whole path.
    fn lookup(&self, path: &str) -> Option<(usize, bool)> {
        let doc = self.doc.as_ref()?;
        let path = parse_path(path)?;
        let mut found: Option<usize> = None;
        let mut depth = 0;
        let mut node = Node::Table(doc.as_table());
        for seg in &path {
            let next = match (seg, node) {
                (Segment::Key(k), Node::Table(t)) => t
                    .get_key_value(k)
                    .map(|(key, it)| (key.span().or_else(|| it.span()), Node::of_item(it))),
                (Segment::Key(k), Node::Inline(t)) => t
                    .get_key_value(k)
                    .map(|(key, it)| (key.span().or_else(|| it.span()), Node::of_item(it))),
                (Segment::Index(i), Node::ArrayOfTables(a)) => {
                    a.get(*i).map(|t| (t.span(), Node::Table(t)))
                }
                (Segment::Index(i), Node::Array(a)) => {
                    a.get(*i).map(|v| (v.span(), Node::of_value(v)))
                }
                _ => None,
            };
            let Some((span, next_node)) = next else { break };
            if let Some(span) = span {
                found = Some(line_column(self.text, span.start).0);
            }
            depth += 1;
            node = next_node;
        }
        found.map(|line| (line, depth == path.len()))
    }
}

/// Where a path lookup stands.
#[derive(Clone, Copy)]
enum Node<'d> {
    Table(&'d Table),
    Inline(&'d InlineTable),
    Array(&'d toml_edit::Array),
    ArrayOfTables(&'d ArrayOfTables),
    Leaf,
}

impl<'d> Node<'d> {
    fn of_item(item: &'d Item) -> Self {
        match item {
            Item::Table(t) => Self::Table(t),
            Item::ArrayOfTables(a) => Self::ArrayOfTables(a),
            Item::Value(v) => Self::of_value(v),
            Item::None => Self::Leaf,
        }
    }
    fn of_value(v: &'d Value) -> Self {
        match v {
            Value::InlineTable(t) => Self::Inline(t),
            Value::Array(a) => Self::Array(a),
            _ => Self::Leaf,
        }
    }
}

fn consider(path: &[Segment], best: &mut Option<Vec<Segment>>) {
    if best.as_ref().is_none_or(|b| path.len() >= b.len()) {
        *best = Some(path.to_vec());
    }
}

fn walk_table(t: &Table, path: &mut Vec<Segment>, offset: usize, best: &mut Option<Vec<Segment>>) {
    for (k, item) in t.iter() {
        path.push(Segment::Key(k.to_owned()));
        if contains(t.key(k).and_then(toml_edit::Key::span), offset) {
            consider(path, best);
        }
        walk_item(item, path, offset, best);
        path.pop();
    }
}

fn walk_inline(
    t: &InlineTable,
    path: &mut Vec<Segment>,
    offset: usize,
    best: &mut Option<Vec<Segment>>,
) {
    for (k, v) in t.iter() {
        path.push(Segment::Key(k.to_owned()));
        if contains(t.key(k).and_then(toml_edit::Key::span), offset) {
            consider(path, best);
        }
        walk_value(v, path, offset, best);
        path.pop();
    }
}

fn walk_value(v: &Value, path: &mut Vec<Segment>, offset: usize, best: &mut Option<Vec<Segment>>) {
    if contains(v.span(), offset) {
        consider(path, best);
    }
    match v {
        Value::InlineTable(t) => walk_inline(t, path, offset, best),
        Value::Array(a) => {
            for (i, v) in a.iter().enumerate() {
                path.push(Segment::Index(i));
                walk_value(v, path, offset, best);
                path.pop();
            }
        }
        _ => {}
    }
}

fn walk_item(item: &Item, path: &mut Vec<Segment>, offset: usize, best: &mut Option<Vec<Segment>>) {
    match item {
        Item::None => {}
        Item::Value(v) => walk_value(v, path, offset, best),
        Item::Table(t) => {
            if contains(t.span(), offset) {
                consider(path, best);
            }
            walk_table(t, path, offset, best);
        }
        Item::ArrayOfTables(a) => {
            for (i, t) in a.iter().enumerate() {
                path.push(Segment::Index(i));
                if contains(t.span(), offset) {
                    consider(path, best);
                }
                walk_table(t, path, offset, best);
                path.pop();
            }
        }
    }
}

//! The layout rule of `src/` (STYLE.md §1, by pipeline stage): every module imports only
//! modules below it, so no modules import each other in a circle. This test reads every
//! `src/**/*.rs`, builds the import graph and names each cycle it finds, with the file and
//! line of every import on it.
//!
//! The graph:
//! - **Nodes**: one per module file. `src/job.rs` is `job`, `src/cache/mod.rs` is `cache`,
//!   `src/cache/record.rs` is `cache::record`. `lib.rs` (the crate root: declarations and re-exports)
//!   and `main.rs` (a separate crate that uses the library) import nothing here. Modules
//!   written inline (`mod x { .. }`) belong to their file's node.
//! - **Edges**: every `use` path and every inline path that starts with `crate::`, `super::`
//!   or `self::` (and, in `use`, a path that starts with the name of a child module), resolved
//!   to the deepest module file it names: `crate::gi::cache::Record` is `gi::cache`,
//!   `crate::scene::Motion` is `scene`. A name that a module re-exports (`pub use
//!   frame::FrameScene` in `scene/mod.rs`) resolves to the module that defines it
//!   (`scene::frame`). `super::` is resolved as Rust does.
//! - **Not edges**: a module's paths into its own submodules (a folder's `mod.rs` declaring,
//!   re-exporting and using its submodules is the folder's own structure); a submodule's use
//!   of its parent's `mod.rs` is an edge child → parent, so a child and its parent alone never
//!   make a cycle. Paths in comments and string literals. The item after `#[cfg(test)]` (a
//!   `mod tests { .. }` block, a test-only `use`, fn, or `mod x;` file): tests may import
//!   upward. Detected on tokens: after the attribute `#[cfg(test)]` (and any attributes that
//!   follow it) the item runs to the first `;`, or to the `}` that closes its first `{`.
//!   Other cfg forms (`cfg(any(test, ..))`) are not skipped.
//!
//! The check, at two granularities: the top-level modules, each taken whole (`gi` with all
//! its files), must not import each other in a circle (`render` → `job` → `gi` → `render`
//! fails whichever files of `gi` make the edges); and inside each folder, its direct
//! submodules and its `mod.rs` must not either (`gi::cache` → `gi::photons` → `gi::cache`
//! fails).

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::path::Path;

use super::common::root;

/// Every `src/**/*.rs` as (path relative to `src/` with `/` separators, text), sorted.
fn read_src(dir: &Path) -> Vec<(String, String)> {
    fn walk(dir: &Path, prefix: &str, out: &mut Vec<(String, String)>) {
        let mut entries: Vec<_> = std::fs::read_dir(dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| e.unwrap().path())
            .collect();
        entries.sort();
        for p in entries {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            let rel = format!("{prefix}{name}");
            if p.is_dir() {
                walk(&p, &format!("{rel}/"), out);
            } else if name.ends_with(".rs") {
                out.push((rel, std::fs::read_to_string(&p).unwrap()));
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, "", &mut out);
    out
}

/// The module a file under `src/` defines: `Some("")` for the crate root `lib.rs`, `None` for
/// `main.rs` (the binary crate).
fn module_of(rel: &str) -> Option<String> {
    match rel {
        "lib.rs" => Some(String::new()),
        "main.rs" => None,
        _ => {
            let stem = rel.strip_suffix(".rs")?;
            let stem = stem.strip_suffix("/mod").unwrap_or(stem);
            Some(stem.replace('/', "::"))
        }
    }
}

/// `text` with comments, string literals and char literals replaced by spaces (newlines kept,
/// so that line numbers still hold).
fn strip(text: &str) -> String {
    let c: Vec<char> = text.chars().collect();
    let mut out = c.clone();
    let blank = |out: &mut Vec<char>, from: usize, to: usize| {
        for ch in &mut out[from..to.min(c.len())] {
            if *ch != '\n' {
                *ch = ' ';
            }
        }
    };
    let ident = |i: usize| c[i].is_alphanumeric() || c[i] == '_';
    let mut i = 0;
    while i < c.len() {
        let next = c.get(i + 1).copied();
        if c[i] == '/' && next == Some('/') {
            let end = (i..c.len()).find(|&j| c[j] == '\n').unwrap_or(c.len());
            blank(&mut out, i, end);
            i = end;
        } else if c[i] == '/' && next == Some('*') {
            let (mut depth, mut j) = (1, i + 2);
            while j < c.len() && depth > 0 {
                if c[j] == '/' && c.get(j + 1) == Some(&'*') {
                    depth += 1;
                    j += 2;
                } else if c[j] == '*' && c.get(j + 1) == Some(&'/') {
                    depth -= 1;
                    j += 2;
                } else {
                    j += 1;
                }
            }
            blank(&mut out, i, j);
            i = j;
        } else if c[i] == 'r'
            && (i == 0 || !ident(i - 1) || (c[i - 1] == 'b' && (i < 2 || !ident(i - 2))))
            && matches!(next, Some('"') | Some('#'))
        {
            // Raw string r"..", r#".."#, br#".."#; else the identifier r or r#ident.
            let hashes = (i + 1..c.len()).take_while(|&j| c[j] == '#').count();
            if c.get(i + 1 + hashes) != Some(&'"') {
                i += 1;
                continue;
            }
            let mut j = i + 2 + hashes;
            while j < c.len()
                && !(c[j] == '"' && (0..hashes).all(|k| c.get(j + 1 + k) == Some(&'#')))
            {
                j += 1;
            }
            blank(&mut out, i, j + 1 + hashes);
            i = j + 1 + hashes;
        } else if c[i] == '"' {
            let mut j = i + 1;
            while j < c.len() && c[j] != '"' {
                j += if c[j] == '\\' { 2 } else { 1 };
            }
            blank(&mut out, i, j + 1);
            i = j + 1;
        } else if c[i] == '\'' && next == Some('\\') {
            let end = (i + 3..c.len()).find(|&j| c[j] == '\'').unwrap_or(c.len());
            blank(&mut out, i, end + 1);
            i = end + 1;
        } else if c[i] == '\'' && c.get(i + 2) == Some(&'\'') {
            blank(&mut out, i, i + 3);
            i += 3;
        } else {
            i += 1;
        }
    }
    out.into_iter().collect()
}

/// A token of stripped source: an identifier or number, `::`, or one other character.
#[derive(Clone, Debug)]
struct Token {
    text: String,
    line: usize,
}

fn tokens(code: &str) -> Vec<Token> {
    let mut out = Vec::new();
    for (n, line) in code.lines().enumerate() {
        let c: Vec<char> = line.chars().collect();
        let mut i = 0;
        while i < c.len() {
            let start = i;
            if c[i].is_whitespace() {
                i += 1;
                continue;
            } else if c[i].is_alphanumeric() || c[i] == '_' {
                while i < c.len() && (c[i].is_alphanumeric() || c[i] == '_') {
                    i += 1;
                }
            } else if c[i] == ':' && c.get(i + 1) == Some(&':') {
                i += 2;
            } else {
                i += 1;
            }
            out.push(Token {
                text: c[start..i].iter().collect(),
                line: n + 1,
            });
        }
    }
    out
}

/// `toks` without the items under `#[cfg(test)]`, and the names of test-only file modules
/// (`#[cfg(test)] mod x;`).
fn drop_test_items(toks: Vec<Token>) -> (Vec<Token>, Vec<String>) {
    let is = |i: usize, s: &str| toks.get(i).is_some_and(|t| t.text == s);
    let cfg_test = |i: usize| {
        ["#", "[", "cfg", "(", "test", ")", "]"]
            .iter()
            .enumerate()
            .all(|(k, s)| is(i + k, s))
    };
    // The end (exclusive) of the bracketed group opening at `i`.
    let group_end = |mut i: usize| {
        let mut depth = 0i32;
        while i < toks.len() {
            match toks[i].text.as_str() {
                "(" | "[" | "{" => depth += 1,
                ")" | "]" | "}" => depth -= 1,
                _ => {}
            }
            i += 1;
            if depth == 0 {
                break;
            }
        }
        i
    };
    let (mut kept, mut test_mods) = (Vec::new(), Vec::new());
    let mut i = 0;
    while i < toks.len() {
        if !cfg_test(i) {
            kept.push(toks[i].clone());
            i += 1;
            continue;
        }
        let mut j = i + 7;
        while is(j, "#") && is(j + 1, "[") {
            j = group_end(j + 1);
        }
        let item = j;
        while j < toks.len() && !is(j, ";") && !is(j, "{") {
            j = if is(j, "(") || is(j, "[") {
                group_end(j)
            } else {
                j + 1
            };
        }
        if is(j, ";") {
            let words: Vec<&str> = toks[item..j].iter().map(|t| t.text.as_str()).collect();
            if let Some(k) = words.iter().position(|w| *w == "mod")
                && let Some(name) = words.get(k + 1)
            {
                test_mods.push(name.to_string());
            }
            i = j + 1;
        } else {
            i = group_end(j);
        }
    }
    (kept, test_mods)
}

/// A path as written in the source, at a line; `public` for paths of `pub use`.
#[derive(Clone, Debug)]
struct PathRef {
    segments: Vec<String>,
    alias: Option<String>,
    line: usize,
    in_use: bool,
    public: bool,
}

/// Flattens the use tree starting at `toks[*i]` into `out`, each path prefixed by `prefix`.
fn use_tree(
    toks: &[Token],
    i: &mut usize,
    prefix: Vec<String>,
    out: &mut Vec<(Vec<String>, Option<String>)>,
) {
    let mut path = prefix;
    while *i < toks.len() {
        match toks[*i].text.as_str() {
            "{" => {
                *i += 1;
                while *i < toks.len() && toks[*i].text != "}" {
                    use_tree(toks, i, path.clone(), out);
                    if *i < toks.len() && toks[*i].text == "," {
                        *i += 1;
                    }
                }
                *i += 1;
                return;
            }
            "*" => {
                *i += 1;
                path.push("*".into());
                out.push((path, None));
                return;
            }
            "::" => *i += 1,
            s if s.starts_with(|c: char| c.is_alphabetic() || c == '_') => {
                path.push(s.to_string());
                *i += 1;
                if toks.get(*i).is_some_and(|t| t.text == "::") {
                    continue;
                }
                let mut alias = None;
                if toks.get(*i).is_some_and(|t| t.text == "as") {
                    alias = toks.get(*i + 1).map(|t| t.text.clone());
                    *i += 2;
                }
                if path.last().is_some_and(|s| s == "self") {
                    path.pop();
                }
                out.push((path, alias));
                return;
            }
            _ => return,
        }
    }
}

/// Every `use` path and every inline `crate::` / `super::` / `self::` path of a file.
fn path_refs(toks: &[Token]) -> Vec<PathRef> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < toks.len() {
        let t = &toks[i];
        // `use` opens an import where an item may start (not in `impl Trait + use<'a>`).
        let item_start = i == 0
            || matches!(
                toks[i - 1].text.as_str(),
                ";" | "{" | "}" | "]" | "pub" | ")"
            );
        if t.text == "use" && item_start {
            let public = i >= 1
                && (toks[i - 1].text == "pub"
                    || (toks[i - 1].text == ")"
                        && (0..i)
                            .rev()
                            .find(|&k| toks[k].text == "(")
                            .is_some_and(|k| k >= 1 && toks[k - 1].text == "pub")));
            let line = t.line;
            i += 1;
            let mut paths = Vec::new();
            use_tree(toks, &mut i, Vec::new(), &mut paths);
            for (segments, alias) in paths {
                out.push(PathRef {
                    segments,
                    alias,
                    line,
                    in_use: true,
                    public,
                });
            }
            while i < toks.len() && toks[i].text != ";" {
                i += 1;
            }
            continue;
        }
        let starts_path = matches!(t.text.as_str(), "crate" | "super" | "self")
            && toks.get(i + 1).is_some_and(|n| n.text == "::")
            && !(i >= 1 && (toks[i - 1].text == "::" || toks[i - 1].text == "in"));
        if starts_path {
            let mut segments = vec![t.text.clone()];
            let mut j = i + 1;
            while toks.get(j).is_some_and(|n| n.text == "::")
                && toks
                    .get(j + 1)
                    .is_some_and(|n| n.text.starts_with(|c: char| c.is_alphabetic() || c == '_'))
            {
                segments.push(toks[j + 1].text.clone());
                j += 2;
            }
            out.push(PathRef {
                segments,
                alias: None,
                line: t.line,
                in_use: false,
                public: false,
            });
            i = j;
            continue;
        }
        i += 1;
    }
    out
}

/// An import of one module by another, with where it is written.
#[derive(Clone, Debug)]
struct Evidence {
    file: String,
    line: usize,
    path: String,
}

/// The import graph of a crate's modules.
struct ModuleGraph {
    /// Every module file (lib.rs, the root `""`, included).
    modules: BTreeSet<String>,
    /// Imports between module files.
    edges: Edges,
}

fn parent(module: &str) -> Option<String> {
    if module.is_empty() {
        None
    } else {
        Some(
            module
                .rsplit_once("::")
                .map_or(String::new(), |(p, _)| p.to_string()),
        )
    }
}

fn child(module: &str, name: &str) -> String {
    if module.is_empty() {
        name.to_string()
    } else {
        format!("{module}::{name}")
    }
}

/// True when `module` lies strictly under `ancestor` (everything lies under the root `""`).
fn is_descendant(module: &str, ancestor: &str) -> bool {
    ancestor.is_empty() && !module.is_empty() || module.starts_with(&format!("{ancestor}::"))
}

impl ModuleGraph {
    /// The graph of `files`: (path relative to `src/`, text) pairs.
    fn new(files: &[(String, String)]) -> ModuleGraph {
        struct Parsed {
            file: String,
            module: String,
            refs: Vec<PathRef>,
        }
        let mut parsed = Vec::new();
        let mut test_only = BTreeSet::new();
        for (rel, text) in files {
            let Some(module) = module_of(rel) else {
                continue;
            };
            let (toks, test_mods) = drop_test_items(tokens(&strip(text)));
            test_only.extend(test_mods.iter().map(|m| child(&module, m)));
            parsed.push(Parsed {
                file: format!("src/{rel}"),
                module,
                refs: path_refs(&toks),
            });
        }
        parsed.retain(|p| {
            !test_only
                .iter()
                .any(|t| p.module == *t || is_descendant(&p.module, t))
        });
        let modules: BTreeSet<String> = parsed.iter().map(|p| p.module.clone()).collect();

        // Names re-exported by `pub use`, resolved to the module that defines them; a few
        // rounds so that re-exports of re-exports resolve too.
        let mut reexports: BTreeMap<(String, String), String> = BTreeMap::new();
        for _ in 0..4 {
            for p in &parsed {
                for r in p.refs.iter().filter(|r| r.in_use && r.public) {
                    let Some(name) = r.alias.clone().or_else(|| r.segments.last().cloned()) else {
                        continue;
                    };
                    if name == "*" {
                        continue;
                    }
                    if let Some(target) = resolve(&modules, &reexports, &p.module, r) {
                        reexports.insert((p.module.clone(), name), target);
                    }
                }
            }
        }

        let mut edges = Edges::new();
        for p in parsed.iter().filter(|p| !p.module.is_empty()) {
            let out = edges.entry(p.module.clone()).or_default();
            for r in &p.refs {
                let Some(target) = resolve(&modules, &reexports, &p.module, r) else {
                    continue;
                };
                if target.is_empty() || target == p.module || is_descendant(&target, &p.module) {
                    continue;
                }
                out.entry(target).or_insert_with(|| Evidence {
                    file: p.file.clone(),
                    line: r.line,
                    path: r.segments.join("::"),
                });
            }
        }
        ModuleGraph { modules, edges }
    }

    /// The scopes checked: the crate root (its units are the top-level modules) and every
    /// folder module (its units are its direct submodules and its own `mod.rs`).
    fn scopes(&self) -> Vec<String> {
        let mut scopes = vec![String::new()];
        scopes.extend(
            self.modules
                .iter()
                .filter(|m| !m.is_empty() && self.modules.iter().any(|d| is_descendant(d, m)))
                .cloned(),
        );
        scopes
    }

    /// The imports between the units of `scope`: each module inside it stands for the direct
    /// submodule of `scope` that holds it (or for `scope` itself); each edge keeps the first
    /// import that makes it.
    fn scope_edges(&self, scope: &str) -> Edges {
        let unit = |m: &str| -> Option<String> {
            if m == scope {
                return Some(m.to_string());
            }
            if !is_descendant(m, scope) {
                return None;
            }
            let rest = if scope.is_empty() {
                m
            } else {
                &m[scope.len() + 2..]
            };
            Some(child(scope, rest.split("::").next().unwrap()))
        };
        let mut out = Edges::new();
        for (from, targets) in &self.edges {
            for (to, evidence) in targets {
                if let (Some(a), Some(b)) = (unit(from), unit(to))
                    && a != b
                {
                    out.entry(a)
                        .or_default()
                        .entry(b)
                        .or_insert_with(|| evidence.clone());
                }
            }
        }
        out
    }

    /// Every import cycle: per scope, each set of units that all reach each other, with the
    /// shortest cycle through its first unit.
    fn cycles(&self) -> Vec<Cycle> {
        self.scopes()
            .into_iter()
            .flat_map(|scope| {
                strongly_connected(&self.scope_edges(&scope))
                    .into_iter()
                    .map(move |(members, path)| Cycle {
                        scope: scope.clone(),
                        members,
                        path,
                    })
            })
            .collect()
    }

    /// `cycle` as `a → b → a`, one line per import with the file and line that makes it,
    /// then the other imports inside its set.
    fn describe(&self, cycle: &Cycle) -> String {
        let edges = self.scope_edges(&cycle.scope);
        let path = &cycle.path;
        let mut s = if cycle.scope.is_empty() {
            "between top-level modules: ".to_string()
        } else {
            format!("inside {}: ", cycle.scope)
        };
        s += &format!("{} → {}", path.join(" → "), path[0]);
        let line = |from: &String, to: &String| {
            let e = &edges[from][to];
            format!("\n    {from} → {to}: {}:{} uses {}", e.file, e.line, e.path)
        };
        for (k, from) in path.iter().enumerate() {
            s += &line(from, &path[(k + 1) % path.len()]);
        }
        let on_path = |from: &String, to: &String| {
            (0..path.len()).any(|k| path[k] == *from && path[(k + 1) % path.len()] == *to)
        };
        let others: Vec<String> = cycle
            .members
            .iter()
            .flat_map(|from| {
                edges[from]
                    .keys()
                    .filter(|to| cycle.members.contains(to) && !on_path(from, to))
                    .map(move |to| (from, to))
            })
            .map(|(from, to)| line(from, to))
            .collect();
        if !others.is_empty() {
            s += &format!(
                "\n  other imports among these {} modules, which all reach each other ({}):",
                cycle.members.len(),
                cycle.members.join(", ")
            );
            s += &others.concat();
        }
        s
    }
}

/// Imports: module → imported module → the first import that makes the edge.
type Edges = BTreeMap<String, BTreeMap<String, Evidence>>;

/// A set of modules of one scope (`""`: the top-level modules) that all reach each other,
/// and one cycle through it.
#[derive(Debug)]
struct Cycle {
    scope: String,
    members: Vec<String>,
    path: Vec<String>,
}

/// The strongly connected components of more than one node (Tarjan's algorithm, iteratively),
/// each with the shortest cycle through its first node (breadth-first).
fn strongly_connected(edges: &Edges) -> Vec<(Vec<String>, Vec<String>)> {
    let nodes: BTreeSet<&String> = edges
        .keys()
        .chain(edges.values().flat_map(|m| m.keys()))
        .collect();
    let names: Vec<&String> = nodes.iter().copied().collect();
    let index_of: BTreeMap<&String, usize> =
        names.iter().enumerate().map(|(i, n)| (*n, i)).collect();
    let succ: Vec<Vec<usize>> = names
        .iter()
        .map(|n| {
            edges
                .get(*n)
                .map(|m| m.keys().map(|k| index_of[k]).collect())
                .unwrap_or_default()
        })
        .collect();
    let n = names.len();
    let (mut index, mut low, mut on_stack) = (vec![usize::MAX; n], vec![0; n], vec![false; n]);
    let (mut stack, mut comps, mut next) = (Vec::new(), Vec::new(), 0);
    for root in 0..n {
        if index[root] != usize::MAX {
            continue;
        }
        let mut call: Vec<(usize, usize)> = vec![(root, 0)];
        index[root] = next;
        low[root] = next;
        next += 1;
        stack.push(root);
        on_stack[root] = true;
        while let Some(&(v, k)) = call.last() {
            if k < succ[v].len() {
                call.last_mut().unwrap().1 += 1;
                let w = succ[v][k];
                if index[w] == usize::MAX {
                    index[w] = next;
                    low[w] = next;
                    next += 1;
                    stack.push(w);
                    on_stack[w] = true;
                    call.push((w, 0));
                } else if on_stack[w] {
                    low[v] = low[v].min(index[w]);
                }
                continue;
            }
            call.pop();
            if let Some(&(u, _)) = call.last() {
                low[u] = low[u].min(low[v]);
            }
            if low[v] == index[v] {
                let mut comp = Vec::new();
                while let Some(w) = stack.pop() {
                    on_stack[w] = false;
                    comp.push(w);
                    if w == v {
                        break;
                    }
                }
                if comp.len() > 1 {
                    comps.push(comp);
                }
            }
        }
    }
    let mut out: Vec<(Vec<String>, Vec<String>)> = comps
        .into_iter()
        .map(|comp| {
            let members: BTreeSet<usize> = comp.into_iter().collect();
            let start = *members.iter().next().unwrap();
            // Breadth-first from `start` inside the component, back to `start`.
            let mut prev: BTreeMap<usize, usize> = BTreeMap::new();
            let mut last = start;
            let mut queue = VecDeque::from([start]);
            'search: while let Some(v) = queue.pop_front() {
                for &w in succ[v].iter().filter(|w| members.contains(w)) {
                    if w == start {
                        last = v;
                        break 'search;
                    }
                    if let std::collections::btree_map::Entry::Vacant(e) = prev.entry(w) {
                        e.insert(v);
                        queue.push_back(w);
                    }
                }
            }
            let mut path = vec![last];
            while *path.last().unwrap() != start {
                path.push(prev[path.last().unwrap()]);
            }
            path.reverse();
            (
                members.iter().map(|&i| names[i].clone()).collect(),
                path.into_iter().map(|i| names[i].clone()).collect(),
            )
        })
        .collect();
    out.sort();
    out
}

/// The module file a path names, or `None` for a path outside the crate (another crate, or
/// a name in scope that is no module).
fn resolve(
    modules: &BTreeSet<String>,
    reexports: &BTreeMap<(String, String), String>,
    module: &str,
    r: &PathRef,
) -> Option<String> {
    let mut segs = r.segments.iter().map(String::as_str).peekable();
    let mut at = match *segs.peek()? {
        "crate" => {
            segs.next();
            String::new()
        }
        "self" => {
            segs.next();
            module.to_string()
        }
        "super" => {
            let mut m = module.to_string();
            while segs.peek() == Some(&"super") {
                segs.next();
                m = parent(&m)?;
            }
            m
        }
        // `use child::..` names a child module of this one; anything else is another crate
        // or a name already in scope.
        first if r.in_use && modules.contains(&child(module, first)) => module.to_string(),
        _ => return None,
    };
    for seg in segs {
        let sub = child(&at, seg);
        if modules.contains(&sub) {
            at = sub;
        } else {
            if let Some(target) = reexports.get(&(at.clone(), seg.to_string())) {
                at = target.clone();
            }
            break;
        }
    }
    Some(at)
}

#[test]
fn src_modules_import_each_other_without_cycles() {
    let graph = ModuleGraph::new(&read_src(&root().join("src")));
    let cycles = graph.cycles();
    // Shown when the test fails, for whoever untangles the cycles.
    eprintln!("import graph of src/ (module → the modules it imports):");
    for (from, to) in &graph.edges {
        let to: Vec<&str> = to.keys().map(String::as_str).collect();
        eprintln!("  {from} → {}", to.join(", "));
    }
    let report: Vec<String> = cycles.iter().map(|c| graph.describe(c)).collect();
    assert!(
        cycles.is_empty(),
        "src/ has {} set(s) of modules that import each other in a circle; every module must \
         import only modules below it (tests/it/layout.rs says how the graph is built):\n  {}",
        cycles.len(),
        report.join("\n  ")
    );
}

fn set(files: &[(&str, &str)]) -> Vec<(String, String)> {
    files
        .iter()
        .map(|(p, t)| (p.to_string(), t.to_string()))
        .collect()
}

fn edge_list(g: &ModuleGraph) -> Vec<String> {
    g.edges
        .iter()
        .flat_map(|(a, m)| m.keys().map(move |b| format!("{a}->{b}")))
        .collect()
}

/// A layered crate: a folder whose children use their parent's items and each other, a
/// façade re-export, glob and grouped imports, and upward imports that only tests make.
const LAYERED: &[(&str, &str)] = &[
    (
        "lib.rs",
        "pub mod base;\npub mod geo;\npub mod top;\npub use base::Error;\n",
    ),
    ("main.rs", "use layered::top::run;\nfn main() { run() }\n"),
    (
        "base.rs",
        "pub struct Error;\n#[cfg(test)]\nmod tests {\n    use crate::top::run;\n}\n",
    ),
    (
        "geo/mod.rs",
        "pub mod mesh;\npub mod bvh;\npub use mesh::Mesh;\nuse crate::base;\npub struct Unit;\nfn f() -> bvh::Bvh { todo!() }\n",
    ),
    (
        "geo/mesh.rs",
        "use super::Unit;\nuse crate::{Error, base::*};\n// crate::top::run would be a cycle\nconst S: &str = \"crate::top::run\";\n",
    ),
    (
        "geo/bvh.rs",
        "use super::mesh::Mesh;\npub struct Bvh;\n#[cfg(test)]\nuse crate::top;\n",
    ),
    (
        "top.rs",
        "use crate::geo::{self, Mesh, bvh::Bvh};\npub fn run() { let _ = crate::base::Error; }\n",
    ),
];

#[test]
fn layout_check_passes_a_layered_crate() {
    let g = ModuleGraph::new(&set(LAYERED));
    assert_eq!(
        edge_list(&g),
        [
            "geo->base",
            "geo::bvh->geo::mesh",
            "geo::mesh->base",
            "geo::mesh->geo",
            "top->base",
            "top->geo",
            "top->geo::bvh",
            "top->geo::mesh",
        ]
    );
    assert!(g.cycles().is_empty(), "{:?}", g.cycles());
}

#[test]
fn layout_check_names_a_cycle_between_top_level_modules() {
    let mut files = set(LAYERED);
    // geo::mesh calls up into top, which imports geo.
    files[4].1 += "fn g() { crate::top::run() }\n";
    let g = ModuleGraph::new(&files);
    let cycles = g.cycles();
    assert_eq!(cycles.len(), 1, "{cycles:?}");
    assert_eq!(cycles[0].scope, "");
    assert_eq!(cycles[0].members, ["geo", "top"]);
    assert_eq!(cycles[0].path, ["geo", "top"]);
    let text = g.describe(&cycles[0]);
    assert!(
        text.starts_with("between top-level modules: geo → top → geo"),
        "{text}"
    );
    assert!(
        text.contains("geo → top: src/geo/mesh.rs:5 uses crate::top::run"),
        "{text}"
    );
    assert!(
        text.contains("top → geo: src/top.rs:1 uses crate::geo"),
        "{text}"
    );
}

#[test]
fn layout_check_takes_a_folder_whole_between_top_level_modules() {
    // gi's mod.rs uses its own cache (no edge inside gi), cache uses render, and render uses
    // an item of gi's mod.rs: gi and render import each other.
    let files = set(&[
        ("lib.rs", "pub mod gi;\npub mod render;\n"),
        (
            "gi/mod.rs",
            "pub mod cache;\npub struct Params;\nuse cache::Cache;\n",
        ),
        (
            "gi/cache.rs",
            "use crate::render::shade;\npub struct Cache;\n",
        ),
        ("render.rs", "use crate::gi::Params;\npub fn shade() {}\n"),
    ]);
    let g = ModuleGraph::new(&files);
    let cycles = g.cycles();
    assert_eq!(cycles.len(), 1, "{cycles:?}");
    assert_eq!(
        (cycles[0].scope.as_str(), &cycles[0].path[..]),
        ("", &["gi".to_string(), "render".to_string()][..])
    );
    let text = g.describe(&cycles[0]);
    assert!(
        text.contains("gi → render: src/gi/cache.rs:1 uses crate::render::shade"),
        "{text}"
    );
}

#[test]
fn layout_check_names_a_cycle_inside_a_folder_through_a_reexport() {
    let mut files = set(LAYERED);
    // geo::bvh takes Mesh through geo's re-export; geo::mesh takes Bvh from geo::bvh.
    files[5].1 = files[5]
        .1
        .replace("use super::mesh::Mesh;", "use super::Mesh;");
    files[4].1 += "use super::bvh::Bvh;\n";
    let g = ModuleGraph::new(&files);
    let cycles = g.cycles();
    assert_eq!(cycles.len(), 1, "{cycles:?}");
    assert_eq!(cycles[0].scope, "geo");
    assert_eq!(cycles[0].path, ["geo::bvh", "geo::mesh"]);
    let text = g.describe(&cycles[0]);
    assert!(
        text.starts_with("inside geo: geo::bvh → geo::mesh → geo::bvh"),
        "{text}"
    );
    assert!(
        text.contains("geo::bvh → geo::mesh: src/geo/bvh.rs:1 uses super::Mesh"),
        "{text}"
    );
    assert!(
        text.contains("geo::mesh → geo::bvh: src/geo/mesh.rs:5 uses super::bvh::Bvh"),
        "{text}"
    );
}

#[test]
fn layout_graph_resolves_super_and_skips_test_only_code() {
    // Each test-only import below would close a cycle: a's test file imports c, which imports
    // a; b's test function imports a, which imports b.
    let files = set(&[
        ("lib.rs", "pub mod a;\npub mod b;\npub mod c;\n"),
        ("a/mod.rs", "pub mod x;\npub mod y;\n#[cfg(test)]\nmod t;\n"),
        (
            "a/x.rs",
            "pub(in crate::a) fn f() { super::y::g(); super::super::b::h(); }\n",
        ),
        ("a/y.rs", "pub fn g() {}\n"),
        ("a/t.rs", "use crate::c::uses_a;\n"),
        (
            "b.rs",
            "#[cfg(test)]\n#[allow(unused)]\nfn t(x: [u8; 2]) { let _ = ';'; crate::a::y::g(); }\npub fn h() {}\n",
        ),
        ("c.rs", "pub fn uses_a() { crate::a::y::g() }\n"),
    ]);
    let g = ModuleGraph::new(&files);
    assert_eq!(edge_list(&g), ["a::x->a::y", "a::x->b", "c->a::y"]);
    assert!(g.cycles().is_empty(), "{:?}", g.cycles());
}

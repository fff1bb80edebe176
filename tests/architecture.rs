//! The layers of `docs/architecture.md`, kept by a test (as rust-analyzer's tidy tests and
//! ArchUnit do): every source file is parsed (`syn`), every path it names through `crate::`,
//! `super::`, `librplus::` or `librplus_client::` — in `use` items, expressions, types and macro
//! bodies — is resolved to the module it reaches, and an edge against the order below fails the
//! test, naming the file and line.
//!
//! Bottom to top: `util, assets, mesh → fem → register, input → dataset → phantom`, and
//! `register → gcn → v2s → pipeline → discover → eval → CLI, server`. `register`, `input`, `dataset`,
//! `gcn`, `pipeline`, `discover`, the server and the clients never import `phantom` (what runs in
//! surgery cannot reach how the ground truth was made); `gcn` (inference) never imports `eval`
//! (training) or `dataset` (where the truth is read); the server's library never imports the
//! client crate (its `demo`, part of the binary, replays through it); the OpenIGTLink codec
//! (`igtl/`) imports no crate of the workspace, so it builds and tests alone.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use syn::visit::Visit;

/// The modules of the `librplus` crate each module may import (besides itself).
fn allowed() -> BTreeMap<&'static str, &'static [&'static str]> {
    BTreeMap::from([
        ("util", &[][..]),
        ("mesh", &["util"][..]),
        ("assets", &["util", "mesh"][..]),
        ("fem", &["util", "assets", "mesh"][..]),
        ("register", &["util", "assets", "mesh", "fem"][..]),
        ("input", &["util", "assets", "mesh", "fem", "register"][..]),
        (
            "dataset",
            &["util", "assets", "mesh", "fem", "register"][..],
        ),
        (
            "phantom",
            &["util", "assets", "mesh", "fem", "register", "dataset"][..],
        ),
        ("gcn", &["util", "assets", "mesh", "fem", "register"][..]),
        (
            "v2s",
            &["util", "assets", "mesh", "fem", "register", "gcn"][..],
        ),
        (
            "pipeline",
            &["util", "assets", "mesh", "fem", "register", "gcn", "v2s"][..],
        ),
        (
            "discover",
            &[
                "util", "assets", "mesh", "fem", "register", "input", "dataset", "gcn", "v2s",
                "pipeline",
            ][..],
        ),
        (
            "eval",
            &[
                "util", "assets", "mesh", "fem", "register", "input", "dataset", "gcn", "v2s",
                "pipeline", "discover",
            ][..],
        ),
    ])
}

/// What one file may reach: in its own crate (`crate::`/`super::` paths) and in `librplus` from
/// the other crates.
#[derive(Debug, Clone)]
enum Rule {
    /// A module of the `librplus` library: the modules of `allowed()[layer]`.
    Library { layer: String },
    /// The server's library or the client crate: `librplus` except `phantom`; the server's also
    /// not `librplus_client`, and not `librplus::eval` (it reads datasets from the data layer,
    /// `librplus::dataset`, as the library's surgery path does).
    Service { may_use_client: bool, server: bool },
    /// A binary (the command line, the server's `main` and its demo): anything.
    Binary,
    /// A crate that stands alone (the OpenIGTLink codec): no crate of the workspace.
    Standalone,
}

/// One forbidden edge: `file:line: from → to (path)`.
#[derive(Debug, Clone, PartialEq)]
struct Violation {
    file: String,
    line: usize,
    from: String,
    to: String,
    path: String,
}

impl std::fmt::Display for Violation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}:{}: {} must not import {} (`{}`)",
            self.file, self.line, self.from, self.to, self.path
        )
    }
}

/// The rule and the module path of a file, from where it lies in the repository.
fn classify(rel: &str) -> Option<(Rule, Vec<String>)> {
    let parts: Vec<&str> = rel.split('/').collect();
    match parts.as_slice() {
        ["src", "bin", ..] => Some((Rule::Binary, vec![])),
        ["src", rest @ ..] => {
            let mut module: Vec<String> = rest.iter().map(|s| s.to_string()).collect();
            let last = module.pop()?;
            match last.as_str() {
                "lib.rs" | "mod.rs" => {}
                file => module.push(file.trim_end_matches(".rs").to_string()),
            }
            let layer = module.first().cloned().unwrap_or_else(|| "lib".into());
            Some((Rule::Library { layer }, module))
        }
        ["server", "src", "main.rs" | "demo.rs"] => Some((Rule::Binary, vec![])),
        // The OpenIGTLink bridge is a client of the service (a gRPC session per connection), as
        // the demo is: it may use the client crate, still not `phantom`.
        ["server", "src", "igtl", "bridge.rs"] => Some((
            Rule::Service {
                may_use_client: true,
                server: true,
            },
            vec![],
        )),
        ["server", "src", ..] => Some((
            Rule::Service {
                may_use_client: false,
                server: true,
            },
            vec![],
        )),
        ["igtl", "src", ..] => Some((Rule::Standalone, vec![])),
        ["client", "src", ..] => Some((
            Rule::Service {
                may_use_client: true,
                server: false,
            },
            vec![],
        )),
        _ => None,
    }
}

/// Collects every path of a file with the inline-module nesting it appears in.
struct Paths {
    /// Inline modules (`mod tests { … }`) around the current item.
    inline: Vec<String>,
    /// (line, inline modules, segments).
    found: Vec<(usize, usize, Vec<String>)>,
    /// The lines of `found` inside a `mod tests` (test code), by index into `found`.
    in_tests: Vec<bool>,
}

impl Paths {
    fn push(&mut self, line: usize, segments: Vec<String>) {
        let interesting = matches!(
            segments.first().map(String::as_str),
            Some(
                "crate"
                    | "super"
                    | "librplus"
                    | "librplus_client"
                    | "librplus_server"
                    | "librplus_proto"
            )
        );
        if interesting {
            self.found.push((line, self.inline.len(), segments));
            self.in_tests.push(
                self.inline
                    .iter()
                    .any(|m| m == "tests" || m.ends_with("_tests")),
            );
        }
    }

    fn use_tree(&mut self, prefix: &mut Vec<String>, tree: &syn::UseTree, line: usize) {
        match tree {
            syn::UseTree::Path(p) => {
                prefix.push(p.ident.to_string());
                self.use_tree(prefix, &p.tree, p.ident.span().start().line);
                prefix.pop();
            }
            syn::UseTree::Name(n) => {
                let mut s = prefix.clone();
                s.push(n.ident.to_string());
                self.push(n.ident.span().start().line, s);
            }
            syn::UseTree::Rename(r) => {
                let mut s = prefix.clone();
                s.push(r.ident.to_string());
                self.push(r.ident.span().start().line, s);
            }
            syn::UseTree::Glob(_) => self.push(line, prefix.clone()),
            syn::UseTree::Group(g) => {
                for t in &g.items {
                    self.use_tree(prefix, t, line);
                }
            }
        }
    }
}

impl<'ast> Visit<'ast> for Paths {
    fn visit_item_mod(&mut self, m: &'ast syn::ItemMod) {
        self.inline.push(m.ident.to_string());
        syn::visit::visit_item_mod(self, m);
        self.inline.pop();
    }

    fn visit_item_use(&mut self, u: &'ast syn::ItemUse) {
        let line = u.use_token.span.start().line;
        self.use_tree(&mut Vec::new(), &u.tree, line);
    }

    fn visit_path(&mut self, p: &'ast syn::Path) {
        let segments: Vec<String> = p.segments.iter().map(|s| s.ident.to_string()).collect();
        if let Some(first) = p.segments.first() {
            self.push(first.ident.span().start().line, segments);
        }
        syn::visit::visit_path(self, p);
    }

    fn visit_macro(&mut self, m: &'ast syn::Macro) {
        // Macro bodies are not parsed as Rust: read `a::b::c` runs off their tokens.
        let mut tokens: Vec<proc_macro2::TokenTree> = Vec::new();
        flatten(m.tokens.clone(), &mut tokens);
        let mut i = 0;
        while i < tokens.len() {
            if let proc_macro2::TokenTree::Ident(id) = &tokens[i] {
                let line = id.span().start().line;
                let mut segments = vec![id.to_string()];
                let mut j = i + 1;
                while let (
                    Some(proc_macro2::TokenTree::Punct(a)),
                    Some(proc_macro2::TokenTree::Punct(b)),
                    Some(proc_macro2::TokenTree::Ident(next)),
                ) = (tokens.get(j), tokens.get(j + 1), tokens.get(j + 2))
                {
                    if a.as_char() != ':' || b.as_char() != ':' {
                        break;
                    }
                    segments.push(next.to_string());
                    j += 3;
                }
                if segments.len() > 1 {
                    self.push(line, segments);
                }
                i = j;
            } else {
                i += 1;
            }
        }
        syn::visit::visit_macro(self, m);
    }
}

fn flatten(stream: proc_macro2::TokenStream, out: &mut Vec<proc_macro2::TokenTree>) {
    for t in stream {
        match t {
            proc_macro2::TokenTree::Group(g) => flatten(g.stream(), out),
            other => out.push(other),
        }
    }
}

/// The forbidden edges of one file (`rel`: its path in the repository) with source `text`.
fn violations(rel: &str, text: &str) -> Result<Vec<Violation>, String> {
    let Some((rule, module)) = classify(rel) else {
        return Ok(Vec::new());
    };
    let file = syn::parse_file(text).map_err(|e| format!("{rel}: does not parse: {e}"))?;
    let mut paths = Paths {
        inline: Vec::new(),
        found: Vec::new(),
        in_tests: Vec::new(),
    };
    paths.visit_file(&file);
    let allowed = allowed();
    let mut out = Vec::new();
    for (line, depth, segments) in paths.found {
        let edge = |to: &str| Violation {
            file: rel.to_string(),
            line,
            from: match &rule {
                Rule::Library { layer } => layer.clone(),
                _ => rel.to_string(),
            },
            to: to.to_string(),
            path: segments.join("::"),
        };
        match &rule {
            Rule::Binary => {}
            Rule::Standalone => {
                if segments[0].starts_with("librplus") {
                    out.push(edge(&segments[0]));
                }
            }
            Rule::Service {
                may_use_client,
                server,
            } => match segments[0].as_str() {
                "librplus" if segments.get(1).is_some_and(|m| m == "phantom") => {
                    out.push(edge("librplus::phantom"))
                }
                "librplus" if *server && segments.get(1).is_some_and(|m| m == "eval") => {
                    out.push(edge("librplus::eval"))
                }
                "librplus_client" if !may_use_client => out.push(edge("librplus_client")),
                _ => {}
            },
            Rule::Library { layer } => {
                // The module the path reaches, from the crate root.
                let target = match segments[0].as_str() {
                    "crate" => segments.get(1).cloned(),
                    "super" => {
                        let ups = segments.iter().take_while(|s| *s == "super").count();
                        // The module the path starts in: the file's, then its inline modules.
                        let here = module.len() + depth;
                        if ups > here {
                            return Err(format!("{rel}:{line}: `super` above the crate root"));
                        }
                        if here - ups >= 1 {
                            // Still inside a top-level module: the file's, or (in lib.rs) an
                            // inline one, which belongs to the crate root's own layer.
                            Some(module.first().cloned().unwrap_or_else(|| layer.clone()))
                        } else {
                            segments.get(ups).cloned()
                        }
                    }
                    _ => None,
                };
                let Some(target) = target else { continue };
                if layer == "lib" || &target == layer {
                    continue;
                }
                let Some(ok) = allowed.get(layer.as_str()) else {
                    out.push(Violation {
                        to: format!(
                            "{target} (module `{layer}` has no layer: add it to allowed())"
                        ),
                        ..edge(&target)
                    });
                    continue;
                };
                if allowed.contains_key(target.as_str()) && !ok.contains(&target.as_str()) {
                    out.push(edge(&target));
                }
            }
        }
    }
    Ok(out)
}

fn sources(root: &Path, dir: &str, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(root.join(dir)) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        let rel = p
            .strip_prefix(root)
            .unwrap()
            .to_string_lossy()
            .replace('\\', "/");
        if p.is_dir() {
            sources(root, &rel, out);
        } else if rel.ends_with(".rs") {
            out.push(PathBuf::from(rel));
        }
    }
}

#[test]
fn every_import_follows_the_layers() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = Vec::new();
    for dir in ["src", "server/src", "client/src", "igtl/src"] {
        sources(root, dir, &mut files);
    }
    files.sort();
    assert!(files.len() > 50, "found only {} source files", files.len());
    let mut bad = Vec::new();
    let mut modules = std::collections::BTreeSet::new();
    for rel in &files {
        let rel = rel.to_string_lossy().to_string();
        if let Some((Rule::Library { layer }, _)) = classify(&rel) {
            modules.insert(layer);
        }
        let text = std::fs::read_to_string(root.join(&rel)).unwrap();
        bad.extend(violations(&rel, &text).unwrap());
    }
    // Every top-level module of the library has a place in the order.
    let allowed = allowed();
    let missing: Vec<_> = modules
        .iter()
        .filter(|m| *m != "lib" && !allowed.contains_key(m.as_str()))
        .collect();
    assert!(missing.is_empty(), "modules without a layer: {missing:?}");
    assert!(
        bad.is_empty(),
        "{} import(s) against the layers of DESIGN.md:\n{}",
        bad.len(),
        bad.iter()
            .map(|v| v.to_string())
            .collect::<Vec<_>>()
            .join("\n")
    );
}

#[test]
fn a_planted_back_edge_fails_with_its_file_and_line() {
    // A `use` line, an expression path and a macro body, each against the order.
    let planted = "use crate::mesh::TetMesh;\n\
                   use crate::gcn::model::SrGcn;\n\
                   fn f() {\n    let _ = crate::eval::train::split_scenarios;\n}\n\
                   fn g() {\n    println!(\"{:?}\", crate::phantom::dataset::VERSION);\n}\n";
    let v = violations("src/register/planted.rs", planted).unwrap();
    let got: Vec<(usize, &str)> = v.iter().map(|v| (v.line, v.to.as_str())).collect();
    assert_eq!(got, [(2, "gcn"), (4, "eval"), (7, "phantom")], "{v:?}");
    assert!(
        v[0].to_string()
            .starts_with("src/register/planted.rs:2: register must not import gcn")
    );
    // `super::` climbing out of a nested module to a forbidden sibling.
    let nested = "mod tests {\n    use super::super::super::phantom::truth;\n}\n";
    let v = violations("src/gcn/x.rs", nested).unwrap();
    assert_eq!(v.iter().map(|v| v.line).collect::<Vec<_>>(), [2]);
    // …while `super::*` inside a file's own test module is the file's own layer.
    let own = "mod tests {\n    use super::*;\n    use super::super::sample::SampleData;\n}\n";
    assert!(violations("src/gcn/x.rs", own).unwrap().is_empty());
    // The server's library must not reach the phantom or the client; its binary may.
    let server = "use librplus::phantom::dataset::generate;\nuse librplus_client::replay;\n";
    assert_eq!(
        violations("server/src/service.rs", server).unwrap().len(),
        2
    );
    assert!(violations("server/src/demo.rs", server).unwrap().is_empty());
    // Nor does it read datasets through `eval` (training and evaluation); the client may.
    let eval = "fn f(d: &Path) { let _ = librplus::eval::open(d); }\n";
    assert_eq!(violations("server/src/cases.rs", eval).unwrap().len(), 1);
    assert!(
        violations(
            "server/src/cases.rs",
            &eval.replace("eval", "dataset::read")
        )
        .unwrap()
        .is_empty()
    );
    assert!(
        violations("client/src/messages.rs", eval)
            .unwrap()
            .is_empty()
    );
    // The client may use its own crate name but not the phantom.
    assert_eq!(violations("client/src/replay.rs", server).unwrap().len(), 1);
    // The OpenIGTLink codec stands alone: any crate of the workspace is a violation.
    let codec = "use std::io::Read;\nfn f() { let _ = librplus_proto::v1::Point::default(); }\n";
    let v = violations("igtl/src/point.rs", codec).unwrap();
    assert_eq!(
        v.iter()
            .map(|v| (v.line, v.to.as_str()))
            .collect::<Vec<_>>(),
        [(2, "librplus_proto")]
    );
}

// ---- Circles inside a module, and the server crate's own order ----------------------------

/// The crates whose module graphs are checked for circles: (source folder, crate roots). The
/// library's binary (`src/bin/librplus`) is a crate of its own.
const CRATES: &[(&str, &[&str])] = &[
    ("src", &["lib.rs"]),
    ("src/bin/librplus", &["main.rs"]),
    ("server/src", &["lib.rs", "main.rs"]),
    ("client/src", &["lib.rs", "main.rs"]),
    ("igtl/src", &["lib.rs"]),
];

/// The server library's modules, bottom to top: a module may use the ones before it, never one
/// after it (docs/architecture.md, "The service"). `lib.rs` (the crate root) and the binary
/// (`main.rs`, `demo.rs`) sit above them all.
const SERVER_ORDER: &[&str] = &[
    "error",
    "convert",
    "config",
    "connections",
    "generations",
    "auth",
    "journal",
    "audit",
    "audit_export",
    "store",
    "cases",
    "registry",
    "counted",
    "live",
    "metrics_http",
    "refine",
    "compute",
    "discovery",
    "shared",
    "preload",
    "access",
    "upload",
    "session",
    "service",
    "fuzz",
    "igtl",
];

/// One use of another module inside a crate: `file:line`, from the file's module to the module
/// the path reaches (both as module paths from the crate root).
#[derive(Debug, Clone)]
struct ModEdge {
    file: String,
    line: usize,
    from: Vec<String>,
    to: Vec<String>,
}

/// The module path of a file inside its crate's folder (`a/b.rs` → `[a, b]`, `a/mod.rs` → `[a]`),
/// or None for a crate root.
fn module_of(rel_in_crate: &str, roots: &[&str]) -> Option<Vec<String>> {
    if roots.contains(&rel_in_crate) {
        return None;
    }
    let mut parts: Vec<String> = rel_in_crate
        .trim_end_matches(".rs")
        .split('/')
        .map(str::to_string)
        .collect();
    if parts.last().is_some_and(|l| l == "mod") {
        parts.pop();
    }
    Some(parts)
}

/// The module-to-module uses of the crate in `dir` (test code left out): every `crate::` and
/// `super::` path, resolved to the deepest module of the crate it names.
fn module_edges(
    root: &Path,
    dir: &str,
    roots: &[&str],
    files: &[(String, String)],
) -> Vec<ModEdge> {
    let prefix = format!("{dir}/");
    let in_crate: Vec<(String, Vec<String>, &str)> = files
        .iter()
        .filter_map(|(rel, text)| {
            let inner = rel.strip_prefix(&prefix)?;
            // Files of a nested binary crate (src/bin) are not modules of the library.
            if dir == "src" && inner.starts_with("bin/") {
                return None;
            }
            let module = module_of(inner, roots).unwrap_or_default();
            // Test files (`tests.rs`, `*_tests.rs`) are test code, as `mod tests` is.
            if module
                .last()
                .is_some_and(|m| m == "tests" || m.ends_with("_tests"))
            {
                return None;
            }
            Some((rel.clone(), module, text.as_str()))
        })
        .collect();
    let _ = root;
    let modules: std::collections::BTreeSet<Vec<String>> =
        in_crate.iter().map(|(_, m, _)| m.clone()).collect();
    // The deepest known module a path from the crate root names.
    let deepest = |segs: &[String]| -> Vec<String> {
        (0..=segs.len())
            .rev()
            .map(|k| segs[..k].to_vec())
            .find(|c| modules.contains(c))
            .unwrap_or_default()
    };
    let mut out = Vec::new();
    for (rel, module, text) in &in_crate {
        let Ok(file) = syn::parse_file(text) else {
            continue;
        };
        let mut paths = Paths {
            inline: Vec::new(),
            found: Vec::new(),
            in_tests: Vec::new(),
        };
        paths.visit_file(&file);
        for ((line, depth, segments), test) in paths.found.iter().zip(&paths.in_tests) {
            if *test {
                continue;
            }
            let absolute: Vec<String> = match segments[0].as_str() {
                "crate" => segments[1..].to_vec(),
                "super" => {
                    let ups = segments.iter().take_while(|s| *s == "super").count();
                    if ups <= *depth {
                        continue; // inside this file
                    }
                    let climb = ups - depth;
                    if climb > module.len() {
                        continue;
                    }
                    let mut p = module[..module.len() - climb].to_vec();
                    p.extend(segments[ups..].iter().cloned());
                    p
                }
                _ => continue,
            };
            let to = deepest(&absolute);
            if &to != module {
                out.push(ModEdge {
                    file: rel.clone(),
                    line: *line,
                    from: module.clone(),
                    to,
                });
            }
        }
    }
    out
}

/// Circles between sibling modules: for each pair of modules with a common parent, the use
/// lifted to the two children of that parent (a child using its parent's items, or a parent its
/// children, is no edge). Each circle: the children in order, with one use for each step.
fn circles(edges: &[ModEdge]) -> Vec<String> {
    use std::collections::{BTreeMap, BTreeSet};
    // parent → child → (child it uses → first use).
    let mut graph: BTreeMap<Vec<String>, BTreeMap<String, BTreeMap<String, String>>> =
        BTreeMap::new();
    for e in edges {
        let common = e.from.iter().zip(&e.to).take_while(|(a, b)| a == b).count();
        if common >= e.from.len() || common >= e.to.len() {
            continue;
        }
        let parent = e.from[..common].to_vec();
        graph
            .entry(parent)
            .or_default()
            .entry(e.from[common].clone())
            .or_default()
            .entry(e.to[common].clone())
            .or_insert_with(|| format!("{}:{}", e.file, e.line));
    }
    let mut out = Vec::new();
    for (parent, g) in &graph {
        // A circle exists where a child reaches itself; report each strongly connected set once.
        let reach = |from: &str| -> BTreeSet<String> {
            let mut seen = BTreeSet::new();
            let mut stack = vec![from.to_string()];
            while let Some(n) = stack.pop() {
                for m in g
                    .get(&n)
                    .map(|x| x.keys().cloned().collect::<Vec<_>>())
                    .unwrap_or_default()
                {
                    if seen.insert(m.clone()) {
                        stack.push(m);
                    }
                }
            }
            seen
        };
        let mut done = BTreeSet::new();
        for child in g.keys() {
            if done.contains(child) || !reach(child).contains(child) {
                continue;
            }
            // The shortest way back to `child` (breadth first), named by its uses.
            let mut prev: BTreeMap<String, String> = BTreeMap::new();
            let mut queue = std::collections::VecDeque::from([child.clone()]);
            'search: while let Some(n) = queue.pop_front() {
                for m in g
                    .get(&n)
                    .map(|x| x.keys().cloned().collect::<Vec<_>>())
                    .unwrap_or_default()
                {
                    if m == *child {
                        prev.insert(m, n);
                        break 'search;
                    }
                    if !prev.contains_key(&m) {
                        prev.insert(m.clone(), n.clone());
                        queue.push_back(m);
                    }
                }
            }
            let mut cycle = vec![child.clone()];
            let mut at = prev[child].clone();
            while at != *child {
                cycle.push(at.clone());
                at = prev[&at].clone();
            }
            cycle.reverse();
            let scope = if parent.is_empty() {
                "the crate root".to_string()
            } else {
                format!("module `{}`", parent.join("::"))
            };
            let steps: Vec<String> = (0..cycle.len())
                .map(|i| {
                    let (a, b) = (&cycle[i], &cycle[(i + 1) % cycle.len()]);
                    format!("{a} → {b} ({})", g[a][b])
                })
                .collect();
            for c in &cycle {
                done.insert(c.clone());
            }
            out.push(format!("a circle inside {scope}: {}", steps.join(", ")));
        }
    }
    out
}

/// Uses inside the server's library against [`SERVER_ORDER`] (a lower module using a higher
/// one), and modules missing from the order.
fn server_back_edges(edges: &[ModEdge]) -> Vec<String> {
    let rank = |m: &str| SERVER_ORDER.iter().position(|x| *x == m);
    let mut out = Vec::new();
    for e in edges {
        let (Some(from), Some(to)) = (e.from.first(), e.to.first()) else {
            continue; // the crate root uses anything
        };
        if from == to || from == "main" || from == "demo" {
            continue;
        }
        match (rank(from), rank(to)) {
            (Some(a), Some(b)) if a < b => out.push(format!(
                "{}:{}: `{from}` must not use `{to}`, which sits above it in the server's order",
                e.file, e.line
            )),
            (None, _) => out.push(format!(
                "{}: module `{from}` has no place in SERVER_ORDER (tests/architecture.rs)",
                e.file
            )),
            (_, None) if to != "main" && to != "demo" => out.push(format!(
                "{}: module `{to}` has no place in SERVER_ORDER (tests/architecture.rs)",
                e.file
            )),
            _ => {}
        }
    }
    out.sort();
    out.dedup();
    out
}

/// Every source file of the crates in [`CRATES`], as (path from the repository root, text).
fn crate_files(root: &Path) -> Vec<(String, String)> {
    let mut files = Vec::new();
    for (dir, _) in CRATES {
        if *dir == "src/bin/librplus" {
            continue; // listed under `src`
        }
        sources(root, dir, &mut files);
    }
    files.sort();
    files.dedup();
    files
        .into_iter()
        .map(|rel| {
            let rel = rel.to_string_lossy().to_string();
            let text = std::fs::read_to_string(root.join(&rel)).unwrap();
            (rel, text)
        })
        .collect()
}

#[test]
fn no_circles_inside_modules_and_the_server_keeps_its_order() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let files = crate_files(root);
    assert!(files.len() > 100, "found only {} source files", files.len());
    let mut bad = Vec::new();
    for (dir, roots) in CRATES {
        let edges = module_edges(root, dir, roots, &files);
        bad.extend(circles(&edges));
        if *dir == "server/src" {
            bad.extend(server_back_edges(&edges));
        }
    }
    assert!(
        bad.is_empty(),
        "{} problem(s) with the module structure:\n{}",
        bad.len(),
        bad.join("\n")
    );
}

#[test]
fn a_planted_circle_and_a_planted_back_edge_are_found_with_file_and_line() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let f = |rel: &str, text: &str| (rel.to_string(), text.to_string());
    // Two siblings of `mesh` using each other: once through `crate::`, once through `super::`.
    let files = vec![
        f("src/mesh/mod.rs", "pub mod a;\npub mod b;\n"),
        f("src/mesh/a.rs", "use crate::mesh::b::B;\npub struct A;\n"),
        f(
            "src/mesh/b.rs",
            "pub struct B;\n\nfn f() -> super::a::A {\n    super::a::A\n}\n",
        ),
        // Test code does not count.
        f(
            "src/fem/x.rs",
            "pub struct X;\n#[cfg(test)]\nmod tests {\n    use crate::fem::y::Y;\n}\n",
        ),
        f("src/fem/y.rs", "use super::x::X;\npub struct Y;\n"),
    ];
    let edges = module_edges(root, "src", &["lib.rs"], &files);
    let c = circles(&edges);
    assert_eq!(c.len(), 1, "{c:?}");
    assert!(
        c[0].contains("inside module `mesh`")
            && c[0].contains("a → b (src/mesh/a.rs:1)")
            && c[0].contains("b → a (src/mesh/b.rs:3)"),
        "{}",
        c[0]
    );
    // The server: `error` (bottom) using `service` (top) is a back edge, named with its line.
    let files = vec![
        f(
            "server/src/error.rs",
            "pub struct E;\n\nfn g() {\n    crate::service::short(\"x\", 3);\n}\n",
        ),
        f(
            "server/src/service.rs",
            "use crate::error::E;\npub fn short() {}\n",
        ),
    ];
    let edges = module_edges(root, "server/src", &["lib.rs", "main.rs"], &files);
    let back = server_back_edges(&edges);
    assert_eq!(back.len(), 1, "{back:?}");
    assert!(
        back[0].starts_with("server/src/error.rs:4: `error` must not use `service`"),
        "{}",
        back[0]
    );
    // A circle inside the server is a circle too.
    let files = vec![
        f("server/src/upload.rs", "use crate::service::Svc;\n"),
        f(
            "server/src/service.rs",
            "fn h() { crate::upload::create(); }\n",
        ),
    ];
    let edges = module_edges(root, "server/src", &["lib.rs", "main.rs"], &files);
    assert_eq!(circles(&edges).len(), 1);
}

//! Sizes a newcomer can read (`docs/architecture.md`, "Sizes"): no function outside tests longer
//! than 150 lines, none on the surgery path longer than 80, and no source file longer than 900
//! lines. A function is measured from its `fn` keyword to its closing brace; `#[cfg(test)]`
//! modules and the files named `tests.rs` or `*_tests.rs` are test code and not measured.

use std::path::Path;
use syn::visit::Visit;

/// The longest function outside tests (lines).
const FUNCTION_LIMIT: usize = 150;
/// The longest function on the surgery path (lines).
const SURGERY_LIMIT: usize = 80;
/// The longest source file outside `tests/` (lines).
const FILE_LIMIT: usize = 900;

/// What runs while a surgeon waits: measurements in, a registration out. The registration
/// itself (wICP, LIBR, the SR-GCN's inference, the pipeline), measurement input, and the
/// server's streamed session, compute engine, conversions, error mapping and OpenIGTLink bridge.
const SURGERY_PATH: &[&str] = &[
    "src/register/",
    "src/pipeline/",
    "src/gcn/",
    "src/input/",
    "server/src/session/",
    "server/src/compute.rs",
    "server/src/convert.rs",
    "server/src/error.rs",
    "server/src/igtl/",
];

/// Functions still over their limit, each named with its file and the length it may not exceed
/// while it waits to be split; the test fails when one grows, and when one is split (so that
/// it leaves this list). Every other function keeps the limits above.
const NOT_YET_SPLIT: &[(&str, &str, usize)] = &[];

/// The source trees measured.
const TREES: &[&str] = &["src", "server/src", "client/src", "igtl/src", "proto/src"];

/// Every function's (name, first line, length in lines) in a file, test code left out.
#[derive(Default)]
struct Lengths {
    found: Vec<(String, usize, usize)>,
}

fn is_cfg_test(attrs: &[syn::Attribute]) -> bool {
    attrs.iter().any(|a| {
        a.path().is_ident("cfg") && a.parse_args::<syn::Ident>().is_ok_and(|i| i == "test")
    })
}

impl Lengths {
    fn record(&mut self, sig: &syn::Signature, block: &syn::Block) {
        let first = sig.fn_token.span.start().line;
        let last = block.brace_token.span.close().end().line;
        self.found
            .push((sig.ident.to_string(), first, last + 1 - first));
    }
}

impl<'ast> Visit<'ast> for Lengths {
    fn visit_item_mod(&mut self, m: &'ast syn::ItemMod) {
        if !is_cfg_test(&m.attrs) {
            syn::visit::visit_item_mod(self, m);
        }
    }

    fn visit_item_fn(&mut self, f: &'ast syn::ItemFn) {
        if !is_cfg_test(&f.attrs) {
            self.record(&f.sig, &f.block);
            syn::visit::visit_item_fn(self, f);
        }
    }

    fn visit_impl_item_fn(&mut self, f: &'ast syn::ImplItemFn) {
        if !is_cfg_test(&f.attrs) {
            self.record(&f.sig, &f.block);
            syn::visit::visit_impl_item_fn(self, f);
        }
    }

    fn visit_trait_item_fn(&mut self, f: &'ast syn::TraitItemFn) {
        if let Some(block) = &f.default {
            self.record(&f.sig, block);
        }
        syn::visit::visit_trait_item_fn(self, f);
    }
}

/// What is too long in one file (`rel`: its path from the repository root), as `file:line`
/// messages.
fn too_long(rel: &str, text: &str) -> Result<Vec<String>, String> {
    let mut out = Vec::new();
    let lines = text.lines().count();
    if lines > FILE_LIMIT {
        out.push(format!("{rel}: {lines} lines (at most {FILE_LIMIT})"));
    }
    let file = syn::parse_file(text).map_err(|e| format!("{rel}: {e}"))?;
    let mut v = Lengths::default();
    v.visit_file(&file);
    let surgery = SURGERY_PATH.iter().any(|p| rel.starts_with(p));
    let limit = if surgery {
        SURGERY_LIMIT
    } else {
        FUNCTION_LIMIT
    };
    for (name, line, len) in v.found {
        let waiting = NOT_YET_SPLIT
            .iter()
            .find(|(f, n, _)| *f == rel && *n == name)
            .map(|(_, _, max)| *max);
        if let Some(max) = waiting {
            if len > max {
                out.push(format!(
                    "{rel}:{line}: fn {name} grew to {len} lines (listed as waiting to be split at {max})"
                ));
            } else if len <= limit {
                out.push(format!(
                    "{rel}:{line}: fn {name} is {len} lines now: take it off NOT_YET_SPLIT"
                ));
            }
            continue;
        }
        if len > limit {
            let what = if surgery {
                "on the surgery path"
            } else {
                "outside tests"
            };
            out.push(format!(
                "{rel}:{line}: fn {name} is {len} lines (at most {limit} {what})"
            ));
        }
    }
    Ok(out)
}

fn sources(root: &Path, dir: &str, out: &mut Vec<String>) {
    let Ok(entries) = std::fs::read_dir(root.join(dir)) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        let rel = format!("{dir}/{}", e.file_name().to_string_lossy());
        if p.is_dir() {
            sources(root, &rel, out);
        } else if rel.ends_with(".rs") && !rel.ends_with("/tests.rs") && !rel.ends_with("_tests.rs")
        {
            out.push(rel);
        }
    }
}

#[test]
fn functions_and_files_stay_within_their_sizes() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = Vec::new();
    for t in TREES {
        sources(root, t, &mut files);
    }
    files.sort();
    assert!(files.len() > 100, "found only {} source files", files.len());
    let mut bad = Vec::new();
    let mut longest = (String::new(), 0);
    for rel in &files {
        let text = std::fs::read_to_string(root.join(rel)).unwrap();
        bad.extend(too_long(rel, &text).unwrap());
        let lines = text.lines().count();
        if lines > longest.1 {
            longest = (rel.clone(), lines);
        }
    }
    eprintln!(
        "{} source files measured; the longest file {} ({} lines)",
        files.len(),
        longest.0,
        longest.1
    );
    assert!(
        bad.is_empty(),
        "{} too long:\n{}",
        bad.len(),
        bad.join("\n")
    );
}

#[test]
fn a_planted_long_function_is_found_and_test_code_is_not_measured() {
    let body = "    let x = 1;\n".repeat(FUNCTION_LIMIT);
    let text = format!(
        "fn short() {{}}\n\nfn long() {{\n{body}}}\n\n#[cfg(test)]\nmod tests {{\n    fn also_long() {{\n{body}    }}\n}}\n"
    );
    let found = too_long("src/eval/planted.rs", &text).unwrap();
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(
        found[0].starts_with("src/eval/planted.rs:3: fn long is 152 lines"),
        "{}",
        found[0]
    );
    // The same function on the surgery path, and a short one there that is still too long.
    let body = "    let x = 1;\n".repeat(SURGERY_LIMIT);
    let text = format!("impl A {{\n    fn step(&self) {{\n{body}    }}\n}}\n");
    let found = too_long("src/pipeline/planted.rs", &text).unwrap();
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(found[0].contains("fn step is 82 lines (at most 80 on the surgery path)"));
    // A file over the limit.
    let text = "// a line\n".repeat(FILE_LIMIT + 1);
    let found = too_long("src/eval/planted.rs", &text).unwrap();
    assert_eq!(
        found,
        vec![format!(
            "src/eval/planted.rs: {} lines (at most {FILE_LIMIT})",
            FILE_LIMIT + 1
        )]
    );
}

//! Licences of what LIBR+ is built from: every crate in `Cargo.lock` (for Linux x86-64) is under
//! a licence on the project's allow list, and `docs/licences.md` lists exactly those crates with
//! their licences. The list comes from `cargo metadata` (the `license` and `license_file` fields
//! of each crate's manifest); the licence expressions are read as SPDX (`AND` binds tighter than
//! `OR`, `/` is the old spelling of `OR`).
//!
//! When a dependency changes, rewrite the page's crate table with
//! `LIBRPLUS_BLESS=1 cargo test --test licences` and review the diff.

use std::collections::BTreeMap;
use std::fs;
use std::path::PathBuf;
use std::process::Command;

/// Licences every dependency may be under (SPDX identifiers): permissive ones, plus MPL-2.0
/// (file-level copyleft: the crates' sources stay as published on crates.io) and the data
/// licence CDLA-Permissive-2.0 of the Mozilla root certificates.
const ALLOWED: &[&str] = &[
    "MIT",
    "Apache-2.0",
    "Apache-2.0 WITH LLVM-exception",
    "BSD-2-Clause",
    "BSD-3-Clause",
    "ISC",
    "Zlib",
    "Unicode-3.0",
    "Unlicense",
    "CC0-1.0",
    "0BSD",
    "BSL-1.0",
    "MPL-2.0",
    "CDLA-Permissive-2.0",
];

/// Crates whose manifest names a licence file instead of an SPDX expression, with the licence
/// that file was read to be.
const LICENSE_FILES: &[(&str, &str)] = &[("cfg_block", "Apache-2.0")];

const BEGIN: &str =
    "<!-- crates: begin (written by `LIBRPLUS_BLESS=1 cargo test --test licences`) -->";
const END: &str = "<!-- crates: end -->";

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Tokens of an SPDX expression: identifiers (with `WITH x` kept on them), `AND`, `OR`, parens.
fn tokens(expr: &str) -> Vec<String> {
    let spaced = expr
        .replace('/', " OR ")
        .replace('(', " ( ")
        .replace(')', " ) ");
    let mut out: Vec<String> = Vec::new();
    let mut words = spaced.split_whitespace().peekable();
    while let Some(w) = words.next() {
        if w == "WITH" {
            let exception = words.next().unwrap_or("");
            let last = out.last_mut().expect("WITH follows a licence");
            *last = format!("{last} WITH {exception}");
        } else {
            out.push(w.to_string());
        }
    }
    out
}

/// Whether the expression at `t[*i..]` is satisfiable with the allowed licences.
fn or_expr(t: &[String], i: &mut usize) -> Result<bool, String> {
    let mut ok = and_expr(t, i)?;
    while t.get(*i).is_some_and(|w| w == "OR") {
        *i += 1;
        ok |= and_expr(t, i)?;
    }
    Ok(ok)
}

fn and_expr(t: &[String], i: &mut usize) -> Result<bool, String> {
    let mut ok = atom(t, i)?;
    while t.get(*i).is_some_and(|w| w == "AND") {
        *i += 1;
        ok &= atom(t, i)?;
    }
    Ok(ok)
}

fn atom(t: &[String], i: &mut usize) -> Result<bool, String> {
    let w = t.get(*i).ok_or("the expression ends early")?;
    *i += 1;
    if w == "(" {
        let ok = or_expr(t, i)?;
        if t.get(*i).map(String::as_str) != Some(")") {
            return Err("a '(' is not closed".into());
        }
        *i += 1;
        Ok(ok)
    } else if w == ")" || w == "AND" || w == "OR" {
        Err(format!("'{w}' where a licence was expected"))
    } else {
        Ok(ALLOWED.contains(&w.as_str()))
    }
}

/// Whether an SPDX licence expression can be met with the allowed licences.
fn allowed(expr: &str) -> Result<bool, String> {
    let t = tokens(expr);
    let mut i = 0;
    let ok = or_expr(&t, &mut i)?;
    if i != t.len() {
        return Err(format!("unexpected '{}'", t[i]));
    }
    Ok(ok)
}

#[test]
fn spdx_expressions_are_read_with_and_binding_tighter_than_or() {
    assert_eq!(allowed("MIT OR Apache-2.0"), Ok(true));
    assert_eq!(allowed("MIT/Apache-2.0"), Ok(true));
    assert_eq!(allowed("GPL-3.0-only"), Ok(false));
    assert_eq!(allowed("GPL-3.0-only OR MIT"), Ok(true));
    assert_eq!(allowed("GPL-3.0-only AND MIT"), Ok(false));
    // AND first: (MIT AND GPL) OR ISC is allowed through ISC.
    assert_eq!(allowed("MIT AND GPL-3.0-only OR ISC"), Ok(true));
    assert_eq!(allowed("(MIT OR Apache-2.0) AND Unicode-3.0"), Ok(true));
    assert_eq!(allowed("(MIT OR Apache-2.0) AND GPL-2.0"), Ok(false));
    assert_eq!(
        allowed("Apache-2.0 WITH LLVM-exception OR Apache-2.0 OR MIT"),
        Ok(true)
    );
    assert_eq!(allowed("GPL-2.0 WITH Classpath-exception-2.0"), Ok(false));
    assert!(allowed("(MIT OR Apache-2.0").is_err());
    assert!(allowed("MIT OR").is_err());
}

/// (name, version, licence) of every crate LIBR+ is built from, sorted, workspace excluded.
fn crates() -> Vec<(String, String, String)> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .current_dir(root())
        .args([
            "metadata",
            "--locked",
            "--offline",
            "--format-version",
            "1",
            "--filter-platform",
            "x86_64-unknown-linux-gnu",
        ])
        .output()
        .expect("cargo metadata runs");
    assert!(
        out.status.success(),
        "cargo metadata failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let meta: serde_json::Value = serde_json::from_slice(&out.stdout).expect("cargo metadata JSON");
    let members: Vec<&str> = meta["workspace_members"]
        .as_array()
        .expect("workspace_members")
        .iter()
        .filter_map(|v| v.as_str())
        .collect();
    let files: BTreeMap<&str, &str> = LICENSE_FILES.iter().copied().collect();
    let mut list: Vec<(String, String, String)> = meta["packages"]
        .as_array()
        .expect("packages")
        .iter()
        .filter(|p| !members.contains(&p["id"].as_str().unwrap_or("")))
        .map(|p| {
            let name = p["name"].as_str().expect("name").to_string();
            let version = p["version"].as_str().expect("version").to_string();
            let licence = match p["license"].as_str() {
                Some(l) => l.to_string(),
                None => match files.get(name.as_str()) {
                    Some(l) => format!("{l} (from its licence file)"),
                    None => panic!(
                        "crate {name} {version} names no SPDX licence (license_file: {}): read \
                         the file and add it to LICENSE_FILES in tests/licences.rs",
                        p["license_file"]
                    ),
                },
            };
            (name, version, licence)
        })
        .collect();
    list.sort();
    list
}

#[test]
fn every_crate_is_under_an_allowed_licence_and_docs_list_them_all() {
    let list = crates();
    assert!(
        list.len() > 100,
        "only {} crates from cargo metadata",
        list.len()
    );
    let mut bad = Vec::new();
    for (name, version, licence) in &list {
        let expr = licence.trim_end_matches(" (from its licence file)");
        match allowed(expr) {
            Ok(true) => {}
            Ok(false) => bad.push(format!(
                "{name} {version}: {licence} (not on the allow list)"
            )),
            Err(e) => bad.push(format!("{name} {version}: '{licence}' is not SPDX: {e}")),
        }
    }
    assert!(
        bad.is_empty(),
        "crates under licences not allowed:\n{}",
        bad.join("\n")
    );

    let mut table = String::from("| crate | version | licence |\n| --- | --- | --- |\n");
    for (name, version, licence) in &list {
        table.push_str(&format!("| {name} | {version} | {licence} |\n"));
    }
    let path = root().join("docs/licences.md");
    let page = fs::read_to_string(&path).expect("docs/licences.md");
    let (Some(b), Some(e)) = (page.find(BEGIN), page.find(END)) else {
        panic!("docs/licences.md lacks the lines {BEGIN} and {END}");
    };
    let current = &page[b + BEGIN.len()..e];
    let wanted = format!("\n{table}");
    if current != wanted {
        if std::env::var_os("LIBRPLUS_BLESS").is_some() {
            let new = format!("{}{BEGIN}{wanted}{}", &page[..b], &page[e..]);
            fs::write(&path, new).expect("write docs/licences.md");
            println!(
                "docs/licences.md: crate table rewritten ({} crates)",
                list.len()
            );
        } else {
            panic!(
                "docs/licences.md's crate table is not what Cargo.lock holds ({} crates); \
                 rewrite it with `LIBRPLUS_BLESS=1 cargo test --test licences` and review the diff",
                list.len()
            );
        }
    }
}

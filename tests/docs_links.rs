//! The documentation stays navigable: every relative link in README.md, RESULTS.md,
//! BENCHMARKS.md and docs/**/*.md points to a file that exists; the README stays a five-minute read
//! (at most 250 lines); no Markdown table cell in README.md or docs/*.md is longer than 300
//! characters. Std only: the Markdown is scanned here, not rendered.

use std::fs;
use std::path::{Path, PathBuf};

/// Most lines README.md may have.
const README_MAX_LINES: usize = 250;
/// Most characters one table cell may have (about a sentence or two).
const CELL_MAX_CHARS: usize = 300;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `docs/*.md` and the pages of its subfolders (`docs/benchmarks/*.md`), sorted.
fn docs_pages() -> Vec<PathBuf> {
    fn walk(dir: &Path, pages: &mut Vec<PathBuf>) {
        let entries =
            fs::read_dir(dir).unwrap_or_else(|e| panic!("cannot list {}: {e}", dir.display()));
        for e in entries {
            let p = e.expect("a readable entry of docs/").path();
            if p.is_dir() {
                walk(&p, pages);
            } else if p.extension().is_some_and(|x| x == "md") {
                pages.push(p);
            }
        }
    }
    let mut pages = Vec::new();
    walk(&root().join("docs"), &mut pages);
    pages.sort();
    assert!(
        pages.iter().any(|p| p.ends_with("docs/README.md")),
        "docs/ has no README.md"
    );
    pages
}

fn read(path: &Path) -> String {
    fs::read_to_string(path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()))
}

/// The path as the failure messages show it: relative to the repository root.
fn shown(path: &Path) -> String {
    let root = root();
    path.strip_prefix(&root)
        .unwrap_or(path)
        .display()
        .to_string()
}

/// One character per element, with fenced code blocks and inline code spans blanked out (newlines
/// kept, so positions still give line numbers): neither holds links or table cells.
fn without_code(text: &str) -> Vec<char> {
    let mut out = Vec::with_capacity(text.len());
    let mut in_fence: Option<String> = None;
    for line in text.split_inclusive('\n') {
        let trimmed = line.trim_start();
        let fence: String = trimmed
            .chars()
            .take_while(|&c| c == '`' || c == '~')
            .collect();
        let opens = fence.len() >= 3
            && (fence.chars().all(|c| c == '`') || fence.chars().all(|c| c == '~'));
        match &in_fence {
            Some(open) => {
                if opens
                    && fence.starts_with(open.as_str())
                    && trimmed[fence.len()..].trim().is_empty()
                {
                    in_fence = None;
                }
                out.extend(line.chars().map(|c| if c == '\n' { '\n' } else { ' ' }));
            }
            None if opens => {
                in_fence = Some(fence);
                out.extend(line.chars().map(|c| if c == '\n' { '\n' } else { ' ' }));
            }
            None => out.extend(line.chars()),
        }
    }
    blank_code_spans(&mut out);
    out
}

/// Blanks inline code spans: a run of n backticks up to the next run of exactly n backticks in the
/// same paragraph (no blank line between). A run without its closing run stays as it is.
fn blank_code_spans(chars: &mut [char]) {
    let mut i = 0;
    while i < chars.len() {
        if chars[i] != '`' || (i > 0 && chars[i - 1] == '\\') {
            i += 1;
            continue;
        }
        let n = run_at(chars, i);
        let mut j = i + n;
        let mut close = None;
        while j < chars.len() {
            if chars[j] == '\n' && paragraph_ends_after(chars, j) {
                break;
            }
            if chars[j] == '`' {
                let m = run_at(chars, j);
                if m == n {
                    close = Some(j);
                    break;
                }
                j += m;
            } else {
                j += 1;
            }
        }
        match close {
            Some(j) => {
                for c in &mut chars[i..j + n] {
                    if *c != '\n' {
                        *c = ' ';
                    }
                }
                i = j + n;
            }
            None => i += n,
        }
    }
}

/// Length of the run of backticks starting at `i`.
fn run_at(chars: &[char], i: usize) -> usize {
    chars[i..].iter().take_while(|&&c| c == '`').count()
}

/// Whether the line after the newline at `nl` is blank (so the paragraph ends there).
fn paragraph_ends_after(chars: &[char], nl: usize) -> bool {
    chars[nl + 1..]
        .iter()
        .take_while(|&&c| c != '\n')
        .all(|c| c.is_whitespace())
}

/// 1-based line of the character at `index`.
fn line_of(chars: &[char], index: usize) -> usize {
    1 + chars[..index].iter().filter(|&&c| c == '\n').count()
}

/// Index of the bracket closing the one at `open` (`[`…`]` or `(`…`)`), nested pairs skipped,
/// escaped brackets ignored; `None` past a blank line (or, for `(`, past the end of the line).
fn matching(chars: &[char], open: usize) -> Option<usize> {
    let (o, c) = if chars[open] == '[' {
        ('[', ']')
    } else {
        ('(', ')')
    };
    let mut depth = 0usize;
    let mut i = open;
    while i < chars.len() {
        let ch = chars[i];
        let escaped = i > 0 && chars[i - 1] == '\\';
        if ch == '\n' && (o == '(' || paragraph_ends_after(chars, i)) {
            return None;
        }
        if !escaped && ch == o {
            depth += 1;
        } else if !escaped && ch == c {
            depth -= 1;
            if depth == 0 {
                return Some(i);
            }
        }
        i += 1;
    }
    None
}

/// The destination of a link: `<...>` as written, else up to the first space (a title follows).
fn destination(inside: &str) -> String {
    let inside = inside.trim();
    if let Some(rest) = inside.strip_prefix('<') {
        return rest.split('>').next().unwrap_or("").to_string();
    }
    inside.split_whitespace().next().unwrap_or("").to_string()
}

/// Every Markdown link and image `[text](target)` and reference definition `[label]: target`
/// outside code, as (line, target).
fn extract_links(text: &str) -> Vec<(usize, String)> {
    let chars = without_code(text);
    let mut links = Vec::new();
    for i in 0..chars.len() {
        let opens = chars[i] == '[' && (i == 0 || chars[i - 1] != '\\');
        let Some(close) = opens.then(|| matching(&chars, i)).flatten() else {
            continue;
        };
        let target = match chars.get(close + 1) {
            Some('(') => matching(&chars, close + 1).map(|end| &chars[close + 2..end]),
            // A reference definition starts its line.
            Some(':') if i == 0 || chars[i - 1] == '\n' => {
                let rest = &chars[close + 2..];
                let end = rest.iter().position(|&c| c == '\n').unwrap_or(rest.len());
                Some(&rest[..end])
            }
            _ => None,
        };
        if let Some(target) = target {
            let target: String = target.iter().collect();
            links.push((line_of(&chars, i), destination(&target)));
        }
    }
    links
}

/// A target that names a file of this repository (not a web address, mail or in-page anchor),
/// without its `#anchor` or `?query`.
fn relative_path(target: &str) -> Option<&str> {
    let lower = target.to_ascii_lowercase();
    if target.is_empty()
        || target.starts_with('#')
        || lower.starts_with("mailto:")
        || lower.contains("://")
    {
        return None;
    }
    let path = target.split(['#', '?']).next().unwrap_or("");
    (!path.is_empty()).then_some(path)
}

/// "file:line: target" for every relative link in `text` (the contents of `file`) whose target
/// does not exist, resolved against the file's folder (a leading `/`: the repository root).
fn broken_links(file: &Path, text: &str) -> Vec<String> {
    let folder = file.parent().expect("a documentation file has a folder");
    extract_links(text)
        .into_iter()
        .filter_map(|(line, target)| {
            let path = relative_path(&target)?;
            let resolved = match path.strip_prefix('/') {
                Some(from_root) => root().join(from_root),
                None => folder.join(path),
            };
            (!resolved.exists()).then(|| format!("{}:{line}: {target}", shown(file)))
        })
        .collect()
}

/// "file:line: N characters: start…" for every table cell in `text` longer than `max` characters.
fn long_cells(file: &Path, text: &str, max: usize) -> Vec<String> {
    let chars = without_code(text);
    let cleaned: String = chars.iter().collect();
    let mut found = Vec::new();
    // Rows are found outside code; cells are measured on the original line, code spans included.
    for (index, (line, original)) in cleaned.lines().zip(text.lines()).enumerate() {
        if !line.trim().starts_with('|') {
            continue;
        }
        for cell in split_row(original.trim()) {
            let n = cell.chars().count();
            if n > max {
                let start: String = cell.chars().take(60).collect();
                found.push(format!(
                    "{}:{}: {n} characters: {start}…",
                    shown(file),
                    index + 1
                ));
            }
        }
    }
    found
}

/// The cells of a table row `| a | b |`, split at unescaped `|`, trimmed.
fn split_row(row: &str) -> Vec<String> {
    let mut cells = Vec::new();
    let mut cell = String::new();
    let mut previous = ' ';
    for c in row.chars() {
        if c == '|' && previous != '\\' {
            cells.push(cell.trim().to_string());
            cell.clear();
        } else {
            cell.push(c);
        }
        previous = c;
    }
    cells.push(cell.trim().to_string());
    // The text before the first `|` and after the last one is not a cell.
    let inner = cells.len().saturating_sub(1);
    cells.into_iter().take(inner).skip(1).collect()
}

#[test]
fn every_relative_link_points_to_a_file_that_exists() {
    let mut files: Vec<PathBuf> = ["README.md", "RESULTS.md", "BENCHMARKS.md"]
        .iter()
        .map(|f| root().join(f))
        .collect();
    files.extend(docs_pages());
    let mut broken = Vec::new();
    let mut checked = 0;
    for file in &files {
        let text = read(file);
        checked += extract_links(&text).len();
        broken.extend(broken_links(file, &text));
    }
    assert!(
        checked > 0,
        "no link found in {} files: is the extractor broken?",
        files.len()
    );
    assert!(
        broken.is_empty(),
        "links to files that do not exist:\n{}",
        broken.join("\n")
    );
}

#[test]
fn readme_is_short_and_table_cells_are_a_sentence() {
    let readme = root().join("README.md");
    let text = read(&readme);
    let lines = text.lines().count();
    assert!(
        lines <= README_MAX_LINES,
        "README.md has {lines} lines, at most {README_MAX_LINES}: move reference to docs/"
    );
    let mut long = long_cells(&readme, &text, CELL_MAX_CHARS);
    for page in docs_pages() {
        long.extend(long_cells(&page, &read(&page), CELL_MAX_CHARS));
    }
    assert!(
        long.is_empty(),
        "table cells over {CELL_MAX_CHARS} characters (make them paragraphs or lists):\n{}",
        long.join("\n")
    );
}

#[test]
fn the_checks_find_a_planted_broken_link_and_a_long_cell() {
    let text = "# Planted\n\
                A [good link](RESULTS.md#top), [web](https://example.org/x.md), [mail](mailto:a@b),\n\
                [anchor](#planted), `[in code](nowhere-in-code.md)` and ![image](docs/README.md).\n\
                See [the missing\n\
                guide](docs/no-such-page.md#section \"title\").\n\
                \n\
                ```text\n\
                [fenced](also-nowhere.md)\n\
                ```\n\
                [ref]: ./no-such-file.txt\n";
    let links = extract_links(text);
    let targets: Vec<&str> = links.iter().map(|(_, t)| t.as_str()).collect();
    assert_eq!(
        targets,
        [
            "RESULTS.md#top",
            "https://example.org/x.md",
            "mailto:a@b",
            "#planted",
            "docs/README.md",
            "docs/no-such-page.md#section",
            "./no-such-file.txt",
        ]
    );
    let file = root().join("README.md");
    let broken = broken_links(&file, text);
    assert_eq!(
        broken,
        [
            "README.md:4: docs/no-such-page.md#section",
            "README.md:10: ./no-such-file.txt"
        ]
    );

    let long = format!(
        "| a | b |\n| --- | --- |\n| short | {} |\n",
        "x".repeat(301)
    );
    let found = long_cells(&file, &long, CELL_MAX_CHARS);
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(
        found[0].starts_with("README.md:3: 301 characters"),
        "{found:?}"
    );
    // An escaped `|` stays inside its cell.
    assert_eq!(split_row("| a \\| b | c |"), ["a \\| b", "c"]);
}

//! The crate's modules form layers: no module reaches, through `crate::` paths in its product
//! code, a module that reaches it back, and `metrics` imports no runtime part. Read from the
//! sources, so a new edge that closes a cycle fails here before review has to notice it; `mbap`,
//! the one MBAP codec below `net` and `line`, imports nothing of the crate.
//! Test code (`#[cfg(test)]` modules, inline or in their own files) may reach anywhere.

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};

/// Top-level module -> the top-level modules its product code names, each with the files that
/// name it.
type Edges = BTreeMap<String, BTreeMap<String, BTreeSet<String>>>;

/// What `metrics` must never import: the parts that run the gateway, which count into it.
const RUNTIME: &[&str] = &[
    "bus", "dispatch", "net", "tcp", "gateway", "web", "cli", "sim", "routing", "values", "port",
];

#[test]
fn the_crates_modules_have_no_cycle() {
    let edges = edges_of(&source_files());
    if let Some(cycle) = find_cycle(&edges) {
        let steps: Vec<String> = cycle
            .windows(2)
            .map(|pair| {
                let files = &edges[&pair[0]][&pair[1]];
                format!("{} -> {} ({files:?})", pair[0], pair[1])
            })
            .collect();
        panic!("a module cycle:\n  {}", steps.join("\n  "));
    }
}

#[test]
fn metrics_imports_no_runtime_module() {
    let edges = edges_of(&source_files());
    let imported: Vec<&String> = edges
        .get("metrics")
        .map(|to| {
            to.keys()
                .filter(|m| RUNTIME.contains(&m.as_str()))
                .collect()
        })
        .unwrap_or_default();
    assert!(imported.is_empty(), "metrics imports {imported:?}");
}

#[test]
fn the_mbap_codec_imports_no_other_module() {
    // Below both sides that use it (`net`, `line`): a pure codec over bytes.
    let edges = edges_of(&source_files());
    let imported: Vec<&String> = edges
        .get("mbap")
        .map(|to| to.keys().collect())
        .unwrap_or_default();
    assert!(imported.is_empty(), "mbap imports {imported:?}");
}

#[test]
fn the_check_sees_a_cycle_through_a_grouped_import_and_ignores_test_code() {
    let files = vec![
        source(
            "a/mod.rs",
            "use crate::{b::Thing, pdu};\n#[cfg(test)]\nmod tests;\n",
        ),
        source("a/tests.rs", "use crate::c::Helper;\n"),
        source(
            "b.rs",
            "/// Not an edge: crate::c\npub fn f() { crate::c::g() }\n\
             #[cfg(test)]\nmod tests {\n    use crate::a::X;\n    const B: char = '}';\n}\n",
        ),
        source("c.rs", "fn g() -> &'static str { \"crate::b {\" }\n"),
        source("pdu.rs", ""),
    ];
    let edges = edges_of(&files);
    let names = |m: &str| {
        edges
            .get(m)
            .map(|to| to.keys().cloned().collect::<Vec<_>>())
    };
    assert_eq!(names("a"), Some(vec!["b".to_owned(), "pdu".to_owned()]));
    assert_eq!(names("b"), Some(vec!["c".to_owned()]));
    assert_eq!(names("c"), None, "a string is not an edge");
    assert_eq!(find_cycle(&edges), None);
    let mut with_cycle = files;
    with_cycle.push(source("c/more.rs", "use crate::a::Y;\n"));
    let cycle = find_cycle(&edges_of(&with_cycle)).expect("a -> b -> c -> a");
    assert_eq!(cycle.first(), cycle.last());
    assert_eq!(cycle.len(), 4, "{cycle:?}");
}

/// A file of the crate: its path under `src/` and its text.
struct Source {
    path: PathBuf,
    text: String,
}

fn source(path: &str, text: &str) -> Source {
    Source {
        path: PathBuf::from(path),
        text: text.to_owned(),
    }
}

fn source_files() -> Vec<Source> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    let mut dirs = vec![root.clone()];
    while let Some(dir) = dirs.pop() {
        for entry in fs::read_dir(&dir).expect("src/ is readable") {
            let path = entry.expect("a directory entry").path();
            if path.is_dir() {
                dirs.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                let text = fs::read_to_string(&path).expect("a source file");
                let path = path.strip_prefix(&root).expect("under src/").to_path_buf();
                files.push(Source { path, text });
            }
        }
    }
    assert!(files.len() > 20, "found the crate's sources");
    files
}

/// The top-level module a file belongs to (`bus` for `bus/queue/mod.rs`).
fn module_of(path: &Path) -> String {
    let first = path.components().next().expect("a path under src/");
    let name = first.as_os_str().to_string_lossy();
    name.strip_suffix(".rs").unwrap_or(&name).to_owned()
}

fn edges_of(files: &[Source]) -> Edges {
    let test_only = test_only_files(files);
    let mut edges = Edges::new();
    for file in files {
        let module = module_of(&file.path);
        let is_root = matches!(module.as_str(), "lib" | "main");
        if is_root || test_only.iter().any(|t| file.path.starts_with(t)) {
            continue;
        }
        for target in crate_paths(&product_code(&file.text)) {
            if target != module && target != "self" {
                let files = edges.entry(module.clone()).or_default();
                let named_in = files.entry(target).or_default();
                named_in.insert(file.path.display().to_string());
            }
        }
    }
    edges
}

/// Files (or folders) declared by a `#[cfg(test)] mod name;`: test code throughout.
fn test_only_files(files: &[Source]) -> Vec<PathBuf> {
    let mut test_only = Vec::new();
    for file in files {
        let code = without_comments_and_literals(&file.text);
        let mut rest = code.as_str();
        while let Some(at) = rest.find("#[cfg(test)]") {
            rest = &rest[at + "#[cfg(test)]".len()..];
            let declared = rest.trim_start();
            let Some(after_mod) = declared.strip_prefix("mod ") else {
                continue;
            };
            let name: String = after_mod
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            if after_mod[name.len()..].trim_start().starts_with(';') {
                let parent = file.path.parent().unwrap_or(Path::new(""));
                let stem = file.path.file_stem().unwrap_or_default();
                let dir = if matches!(stem.to_str(), Some("mod" | "lib" | "main")) {
                    parent.to_path_buf()
                } else {
                    parent.join(stem)
                };
                test_only.push(dir.join(format!("{name}.rs")));
                test_only.push(dir.join(&name));
            }
        }
    }
    test_only
}

/// `text` without comments, string and character literals, and inline `#[cfg(test)]` modules.
fn product_code(text: &str) -> String {
    let code = without_comments_and_literals(text);
    let mut out = String::with_capacity(code.len());
    let mut rest = code.as_str();
    while let Some(at) = rest.find("#[cfg(test)]") {
        out.push_str(&rest[..at]);
        rest = &rest[at + "#[cfg(test)]".len()..];
        let item = rest.trim_start();
        if let Some(body) = item.strip_prefix("mod ") {
            if let Some(open) = body.find(['{', ';']) {
                if body.as_bytes()[open] == b'{' {
                    let start = item.len() - body.len() + open;
                    rest = &item[start + matching_brace(&item[start..])..];
                }
            }
        }
    }
    out.push_str(rest);
    out
}

/// Where the block opened by the `{` at the start of `code` ends (literals already removed).
fn matching_brace(code: &str) -> usize {
    let mut depth = 0usize;
    for (at, c) in code.char_indices() {
        match c {
            '{' => depth += 1,
            '}' => {
                depth -= 1;
                if depth == 0 {
                    return at + 1;
                }
            }
            _ => {}
        }
    }
    code.len()
}

/// `text` with comments dropped and every string and character literal emptied, so neither a
/// `crate::` in a doc comment nor a brace in a string counts.
fn without_comments_and_literals(text: &str) -> String {
    let chars: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < chars.len() {
        let (c, next) = (chars[i], chars.get(i + 1).copied());
        if c == '/' && next == Some('/') {
            while i < chars.len() && chars[i] != '\n' {
                i += 1;
            }
        } else if c == '/' && next == Some('*') {
            i += 2;
            while i + 1 < chars.len() && !(chars[i] == '*' && chars[i + 1] == '/') {
                i += 1;
            }
            i += 2;
        } else if c == 'r' && matches!(next, Some('"' | '#')) && !ident_before(&chars, i) {
            i = skip_raw_string(&chars, i + 1);
            out.push_str("\"\"");
        } else if c == '"' {
            i += 1;
            while i < chars.len() && chars[i] != '"' {
                i += if chars[i] == '\\' { 2 } else { 1 };
            }
            i += 1;
            out.push_str("\"\"");
        } else if c == '\'' && is_char_literal(&chars, i) {
            i += 1;
            while i < chars.len() && chars[i] != '\'' {
                i += if chars[i] == '\\' { 2 } else { 1 };
            }
            i += 1;
            out.push_str("' '");
        } else {
            out.push(c);
            i += 1;
        }
    }
    out
}

fn ident_before(chars: &[char], at: usize) -> bool {
    at > 0 && (chars[at - 1].is_alphanumeric() || chars[at - 1] == '_')
}

/// Past the raw string whose `#`s or quote start at `at`.
fn skip_raw_string(chars: &[char], mut at: usize) -> usize {
    let hashes = chars[at..].iter().take_while(|&&c| c == '#').count();
    at += hashes + 1;
    while at < chars.len() {
        if chars[at] == '"' && chars[at + 1..].iter().take(hashes).all(|&c| c == '#') {
            let closing = chars[at + 1..].iter().take(hashes).count();
            if closing == hashes {
                return at + 1 + hashes;
            }
        }
        at += 1;
    }
    at
}

/// A `'` that opens a character literal rather than a lifetime: `'x'` or `'\n'`.
fn is_char_literal(chars: &[char], at: usize) -> bool {
    match chars.get(at + 1) {
        Some('\\') => true,
        Some(_) => chars.get(at + 2) == Some(&'\''),
        None => false,
    }
}

/// The top-level modules named by `crate::` paths in `code`, grouped imports included.
fn crate_paths(code: &str) -> BTreeSet<String> {
    let mut named = BTreeSet::new();
    let mut rest = code;
    while let Some(at) = rest.find("crate::") {
        let boundary = at == 0 || !rest[..at].ends_with(|c: char| c.is_alphanumeric() || c == '_');
        rest = &rest[at + "crate::".len()..];
        if !boundary {
            continue;
        }
        if rest.starts_with('{') {
            let group = &rest[1..matching_brace(rest) - 1];
            for item in split_top_level(group) {
                if let Some(name) = leading_ident(item.trim_start()) {
                    named.insert(name);
                }
            }
        } else if let Some(name) = leading_ident(rest) {
            named.insert(name);
        }
    }
    named
}

fn split_top_level(group: &str) -> Vec<&str> {
    let mut items = Vec::new();
    let (mut depth, mut start) = (0i32, 0);
    for (at, c) in group.char_indices() {
        match c {
            '{' => depth += 1,
            '}' => depth -= 1,
            ',' if depth == 0 => {
                items.push(&group[start..at]);
                start = at + 1;
            }
            _ => {}
        }
    }
    items.push(&group[start..]);
    items
}

fn leading_ident(text: &str) -> Option<String> {
    let name: String = text
        .chars()
        .take_while(|c| c.is_alphanumeric() || *c == '_')
        .collect();
    (!name.is_empty() && name.starts_with(|c: char| c.is_lowercase() || c == '_')).then_some(name)
}

/// A cycle among the modules, as the path that closes it (first and last the same), if any.
fn find_cycle(edges: &Edges) -> Option<Vec<String>> {
    fn visit(
        node: &str,
        edges: &Edges,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(at) = path.iter().position(|n| n == node) {
            let mut cycle = path[at..].to_vec();
            cycle.push(node.to_owned());
            return Some(cycle);
        }
        if done.contains(node) {
            return None;
        }
        path.push(node.to_owned());
        for next in edges.get(node).into_iter().flat_map(BTreeMap::keys) {
            if let Some(cycle) = visit(next, edges, path, done) {
                return Some(cycle);
            }
        }
        path.pop();
        done.insert(node.to_owned());
        None
    }
    let mut done = BTreeSet::new();
    edges
        .keys()
        .find_map(|start| visit(start, edges, &mut Vec::new(), &mut done))
}

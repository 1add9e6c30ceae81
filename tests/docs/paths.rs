//! The pages that map the code (docs/architecture.md, docs/development.md) name only paths that
//! exist: every backticked path under `src/`, `config/`, `tests/`, `test-support/`, `bench/` or
//! `docs/` (a folder ends in `/`; a `path:line` or `path::item` suffix is dropped, and so is
//! what follows the first space, a command's arguments) is a file or folder of the repository.
//! A file moved or renamed without its map fails here, naming the page and the path.

use std::path::Path;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// The pages checked.
const PAGES: [&str; 2] = ["docs/architecture.md", "docs/development.md"];

/// What a backticked span must start with to be taken for a path of the repository.
const PREFIXES: [&str; 6] = [
    "src/",
    "config/",
    "tests/",
    "test-support/",
    "bench/",
    "docs/",
];

/// The repository paths `text` names in backticks, outside fenced blocks, in order.
fn paths_in(text: &str) -> Vec<&str> {
    let mut fenced = false;
    let mut found = Vec::new();
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced {
            continue;
        }
        // Between the 1st and 2nd backtick, the 3rd and 4th, ...
        for span in line.split('`').skip(1).step_by(2) {
            let word = span.split_whitespace().next().unwrap_or("");
            if PREFIXES.iter().any(|prefix| word.starts_with(prefix)) {
                // `src/a.rs:12` and `src/a.rs::item` name `src/a.rs`.
                found.push(word.split(':').next().unwrap_or(word));
            }
        }
    }
    found
}

#[test]
fn every_path_the_code_maps_name_exists_in_the_repository() {
    let mut missing = Vec::new();
    let mut checked = 0;
    for page in PAGES {
        let text = std::fs::read_to_string(Path::new(ROOT).join(page))
            .unwrap_or_else(|e| panic!("{page}: {e}"));
        for path in paths_in(&text) {
            let on_disk = Path::new(ROOT).join(path);
            let exists = if path.ends_with('/') {
                on_disk.is_dir()
            } else {
                on_disk.exists()
            };
            if !exists {
                missing.push(format!("{page}: `{path}`"));
            }
            checked += 1;
        }
    }
    assert!(
        missing.is_empty(),
        "paths that do not exist in the repository:\n  {}",
        missing.join("\n  ")
    );
    // The maps name the code's files by the hundred; a handful means the reading broke.
    assert!(checked > 100, "only {checked} paths found in {PAGES:?}");
}

#[test]
fn a_path_is_read_without_its_suffix_and_only_outside_fenced_blocks() {
    let text = "`src/a.rs:12` and `tests/b.rs::f`, `bench/c/` then `cargo test` and `d/e.rs`\n\
                `tests/peers/p.py [rtu|ascii]`\n\
                ```\n`src/fenced.rs`\n```\n\
                last `docs/x.md`, `config/` and `srcs/no.rs`\n";
    assert_eq!(
        paths_in(text),
        [
            "src/a.rs",
            "tests/b.rs",
            "bench/c/",
            "tests/peers/p.py",
            "docs/x.md",
            "config/",
        ]
    );
}

//! Tests wait for events, not for the wall clock: a test that sleeps and then asserts, or that
//! bounds how long something took by the wall clock, passes or fails with the machine's load.
//! Read from the sources of tests/ and test-support/, so a new one fails here, naming its line.
//!
//! Both rules read the code with comments and literals blanked, one function at a time:
//! - sleep: a statement that calls `sleep(` and is followed directly by an assertion
//!   (`assert!`, `assert_eq!`, ...). Wait for the event instead: `within` and a poll of the
//!   state or of `/metrics`. A sleep that is the scenario itself (a gap on a line, a slow peer)
//!   says so in a comment beginning `scenario:`, on its line or on the lines just above it.
//! - bound: an assertion that bounds an elapsed time from above, `x.elapsed() < d` or
//!   `d >= took` where `let took = x.elapsed();`. On tokio's paused clock instead, or against
//!   the gateway's own metrics.
//!
//! A function on the paused clock (`#[tokio::test(start_paused = true)]`, a call of
//! `tokio::time::pause()`, or nested in one) is exempt from both: its sleeps and elapsed times
//! are tokio's virtual ones, exact whatever the load. Its bounds must be on tokio's clock,
//! though: one in a function that takes `std::time::Instant::now()` is a wall-clock bound.

use std::fs;
use std::path::{Path, PathBuf};

#[test]
fn no_test_sleeps_on_the_real_clock_and_then_asserts() {
    let found: Vec<String> = source_files().iter().flat_map(bare_sleeps).collect();
    assert!(
        found.is_empty(),
        "a sleep before an assertion, on the real clock (wait for the event, or mark a \
         scenario's sleep `// scenario: ...`):\n  {}",
        found.join("\n  ")
    );
}

#[test]
fn no_test_bounds_an_elapsed_time_by_the_wall_clock() {
    let found: Vec<String> = source_files().iter().flat_map(wall_clock_bounds).collect();
    assert!(
        found.is_empty(),
        "an upper bound on an elapsed time, on the wall clock (use tokio's paused clock or the \
         gateway's metrics):\n  {}",
        found.join("\n  ")
    );
}

#[test]
fn the_check_finds_a_sleep_before_an_assertion_only_on_the_real_clock() {
    let failing = source(
        "tests/bad.rs",
        "#[tokio::test]\nasync fn polls() {\n    start();\n    \
         tokio::time::sleep(Duration::from_millis(200)).await;\n    \
         assert_eq!(frames(), 0);\n}\n\
         fn helper() {\n    // A sleep in a comment: sleep(1); assert!(x)\n    \
         std::thread::sleep(D);\n\n    assert!(done());\n}\n",
    );
    assert_eq!(
        bare_sleeps(&failing),
        [
            "tests/bad.rs:4: sleep before an assertion",
            "tests/bad.rs:9: sleep before an assertion"
        ]
    );
    let passing = source(
        "tests/good.rs",
        "#[tokio::test(start_paused = true)]\nasync fn on_the_paused_clock() {\n    \
         tokio::time::sleep(D).await;\n    assert!(bus.is_up());\n    \
         let task = tokio::spawn(async move {\n        sleep(D).await;\n        \
         assert!(x);\n    });\n}\n\
         #[tokio::test]\nasync fn paused_by_hand() {\n    tokio::time::pause();\n    \
         sleep(D).await;\n    assert!(x);\n}\n\
         #[tokio::test]\nasync fn a_scenario_and_a_poll() {\n    \
         // scenario: the request in two TCP segments.\n    \
         tokio::time::sleep(GAP).await;\n    assert_eq!(exchange(), REPLY);\n    \
         sleep(GAP).await; // scenario: a slow peer\n    assert!(y);\n    \
         while !done() {\n        sleep(POLL).await;\n    }\n    assert!(z);\n    \
         let text = \"sleep(1); assert!(x);\";\n    \
         within(\"w\", async { sleep(D).await }).await;\n    assert!(w);\n}\n",
    );
    assert_eq!(bare_sleeps(&passing), Vec::<String>::new());
}

#[test]
fn the_check_finds_a_wall_clock_bound_however_it_is_written() {
    let failing = source(
        "tests/bad.rs",
        "#[tokio::test]\nasync fn direct() {\n    let started = Instant::now();\n    \
         assert!(started.elapsed() < Duration::from_millis(900));\n}\n\
         #[tokio::test]\nasync fn through_a_binding() {\n    let took = started.elapsed();\n    \
         assert!(\n        ok && took <= LIMIT,\n        \"{took:?}\"\n    );\n    \
         assert!(LIMIT > started.elapsed().as_millis(), \"reversed\");\n}\n\
         #[tokio::test(start_paused = true)]\nasync fn paused_but_std() {\n    \
         let started = std::time::Instant::now();\n    \
         assert!(started.elapsed() < D);\n}\n",
    );
    assert_eq!(
        wall_clock_bounds(&failing),
        [
            "tests/bad.rs:4: an elapsed time bounded on the wall clock",
            "tests/bad.rs:9: an elapsed time bounded on the wall clock",
            "tests/bad.rs:13: an elapsed time bounded on the wall clock",
            "tests/bad.rs:18: an elapsed time bounded on the wall clock",
        ]
    );
    let passing = source(
        "tests/good.rs",
        "use std::time::{Duration, Instant};\n\
         #[tokio::test(start_paused = true)]\nasync fn paused() {\n    \
         let started = tokio::time::Instant::now();\n    \
         assert!(started.elapsed() < Duration::from_secs(1));\n    \
         let waited = started.elapsed();\n    assert!(waited >= idle && waited <= idle + MS);\n}\n\
         #[tokio::test]\nasync fn lower_bounds_and_loops() {\n    \
         assert!(sent.elapsed() >= Duration::from_micros(17));\n    \
         while start.elapsed() < run_for {\n        poll().await;\n    }\n    \
         if connected.elapsed() < D {\n        return;\n    }\n    \
         assert_eq!(vec.len(), 2, \"elapsed() < 1\");\n    \
         assert!(a < b, \"{:?}\", x.elapsed());\n}\n",
    );
    assert_eq!(wall_clock_bounds(&passing), Vec::<String>::new());
}

/// A file read: its path from the repository root, its text, and its code with every comment
/// and literal blanked (lines kept, so an offset in one is a line in the other).
struct Source {
    path: String,
    code: String,
    comments: Vec<String>,
}

fn source(path: &str, text: &str) -> Source {
    let (code, comments) = lex(text);
    Source {
        path: path.to_owned(),
        code,
        comments,
    }
}

fn source_files() -> Vec<Source> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = Vec::new();
    let mut dirs: Vec<PathBuf> = vec![root.join("tests"), root.join("test-support/src")];
    while let Some(dir) = dirs.pop() {
        for entry in fs::read_dir(&dir).expect("a readable folder") {
            let path = entry.expect("a directory entry").path();
            if path.is_dir() {
                dirs.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                let text = fs::read_to_string(&path).expect("a source file");
                let name = path.strip_prefix(root).expect("in the repository");
                files.push(source(&name.display().to_string(), &text));
            }
        }
    }
    assert!(files.len() > 40, "found the tests' sources");
    files
}

/// `text` with comments and the insides of literals turned to spaces (newlines kept), and
/// each line's comment text.
fn lex(text: &str) -> (String, Vec<String>) {
    let chars: Vec<char> = text.chars().collect();
    let mut code = String::with_capacity(text.len());
    let mut comments = vec![String::new()];
    let blank = |code: &mut String, comments: &mut Vec<String>, c: char| {
        if c == '\n' {
            comments.push(String::new());
        }
        code.push(if c == '\n' { '\n' } else { ' ' });
    };
    let mut i = 0;
    while i < chars.len() {
        let (c, next) = (chars[i], chars.get(i + 1).copied());
        if c == '/' && next == Some('/') {
            while i < chars.len() && chars[i] != '\n' {
                comments.last_mut().expect("a line").push(chars[i]);
                code.push(' ');
                i += 1;
            }
        } else if c == '/' && next == Some('*') {
            let mut depth = 0usize;
            loop {
                if i >= chars.len() {
                    break;
                }
                if chars[i] == '/' && chars.get(i + 1) == Some(&'*') {
                    depth += 1;
                    code.push_str("  ");
                    i += 2;
                } else if chars[i] == '*' && chars.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    code.push_str("  ");
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    blank(&mut code, &mut comments, chars[i]);
                    i += 1;
                }
            }
        } else if let Some(hashes) = raw_string_at(&chars, i) {
            // r"..", r#".."#, br"..": the prefix and quotes kept, the inside blanked.
            let open = i + chars[i..].iter().position(|&c| c == '"').expect("a quote") + 1;
            for &c in &chars[i..open] {
                code.push(c);
            }
            i = open;
            let closing: Vec<char> = std::iter::once('"')
                .chain(std::iter::repeat_n('#', hashes))
                .collect();
            while i < chars.len() && !chars[i..].starts_with(&closing) {
                blank(&mut code, &mut comments, chars[i]);
                i += 1;
            }
            for _ in 0..closing.len().min(chars.len() - i) {
                code.push(chars[i]);
                i += 1;
            }
        } else if c == '"' || (c == '\'' && is_char_literal(&chars, i)) {
            code.push(c);
            i += 1;
            while i < chars.len() && chars[i] != c {
                let step = if chars[i] == '\\' { 2 } else { 1 };
                for &inside in &chars[i..(i + step).min(chars.len())] {
                    blank(&mut code, &mut comments, inside);
                }
                i += step;
            }
            if i < chars.len() {
                code.push(c);
                i += 1;
            }
        } else {
            if c == '\n' {
                comments.push(String::new());
            }
            code.push(c);
            i += 1;
        }
    }
    (code, comments)
}

/// The number of `#`s of the raw string literal starting at `at`, if one does.
fn raw_string_at(chars: &[char], at: usize) -> Option<usize> {
    if at > 0 && is_ident(chars[at - 1]) {
        return None;
    }
    let mut i = at;
    if chars.get(i) == Some(&'b') {
        i += 1;
    }
    if chars.get(i) != Some(&'r') {
        return None;
    }
    let hashes = chars[i + 1..].iter().take_while(|&&c| c == '#').count();
    (chars.get(i + 1 + hashes) == Some(&'"')).then_some(hashes)
}

/// A `'` that opens a character literal rather than a lifetime: `'x'` or `'\n'`.
fn is_char_literal(chars: &[char], at: usize) -> bool {
    match chars.get(at + 1) {
        Some('\\') => true,
        Some(_) => chars.get(at + 2) == Some(&'\''),
        None => false,
    }
}

fn is_ident(c: char) -> bool {
    c.is_alphanumeric() || c == '_'
}

/// A function of a source: where its body is in the code, and whether it runs on the paused
/// clock.
struct Function {
    body: std::ops::Range<usize>,
    paused: bool,
}

fn functions(code: &str) -> Vec<Function> {
    let mut found = Vec::new();
    for at in word_starts(code, "fn") {
        let after = &code[at + 2..];
        if !after.starts_with(char::is_whitespace) {
            continue;
        }
        // The body: the first brace after the signature, unless a `;` ends a declaration first.
        let Some(open) = after.find(['{', ';']) else {
            continue;
        };
        if after.as_bytes()[open] == b';' {
            continue;
        }
        let start = at + 2 + open;
        let end = start + block_len(&code[start..]);
        let body = &code[start..end];
        let paused = attributes_before(&code[..at]).contains("start_paused=true")
            || word_starts(body, "pause")
                .into_iter()
                .any(|p| body[p..].starts_with("pause()") && !body[..p].trim_end().ends_with('.'));
        found.push(Function {
            body: start..end,
            paused,
        });
    }
    found
}

/// Where `word` starts in `code` as a whole identifier.
fn word_starts(code: &str, word: &str) -> Vec<usize> {
    code.match_indices(word)
        .map(|(at, _)| at)
        .filter(|&at| {
            let before = code[..at].chars().next_back();
            let after = code[at + word.len()..].chars().next();
            !before.is_some_and(is_ident) && !after.is_some_and(is_ident)
        })
        .collect()
}

/// The attributes written before an item whose keywords end `before`, whitespace removed.
fn attributes_before(before: &str) -> String {
    let mut rest = before.trim_end();
    for keyword in [
        "async",
        "const",
        "unsafe",
        "pub(crate)",
        "pub(super)",
        "pub",
    ] {
        rest = rest.strip_suffix(keyword).unwrap_or(rest).trim_end();
    }
    let mut attributes = String::new();
    while rest.ends_with(']') {
        let mut depth = 0i32;
        let mut open = None;
        for (at, c) in rest.char_indices().rev() {
            match c {
                ']' => depth += 1,
                '[' => {
                    depth -= 1;
                    if depth == 0 {
                        open = Some(at);
                        break;
                    }
                }
                _ => {}
            }
        }
        let Some(open) = open.filter(|&o| rest[..o].ends_with('#')) else {
            break;
        };
        attributes.extend(rest[open..].chars().filter(|c| !c.is_whitespace()));
        rest = rest[..open - 1].trim_end();
    }
    attributes
}

/// The length of the bracketed group that `code` starts with (`{..}`, `(..)` or `[..]`).
fn block_len(code: &str) -> usize {
    let mut depth = 0i32;
    for (at, c) in code.char_indices() {
        match c {
            '{' | '(' | '[' => depth += 1,
            '}' | ')' | ']' => {
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

/// Whether the code at `at` is in a function on the paused clock.
fn on_paused_clock(functions: &[Function], at: usize) -> bool {
    functions.iter().any(|f| f.paused && f.body.contains(&at))
}

/// The line (from 1) of offset `at`.
fn line_of(code: &str, at: usize) -> usize {
    code[..at].matches('\n').count() + 1
}

fn bare_sleeps(file: &Source) -> Vec<String> {
    let code = &file.code;
    let functions = functions(code);
    let mut found = Vec::new();
    for at in word_starts(code, "sleep") {
        let declared = code[..at].trim_end().ends_with("fn");
        if !code[at + "sleep".len()..].starts_with('(')
            || declared
            || on_paused_clock(&functions, at)
        {
            continue;
        }
        let Some(end) = statement_end(&code[at..]) else {
            continue;
        };
        let next = code[at + end..].trim_start();
        let word: String = next.chars().take_while(|&c| is_ident(c)).collect();
        let is_assertion = word.contains("assert") && next[word.len()..].starts_with('!');
        if is_assertion && !marked_scenario(file, at) {
            let line = line_of(code, at);
            found.push(format!("{}:{line}: sleep before an assertion", file.path));
        }
    }
    found
}

/// Past the `;` that ends the statement `code` is in, if a `;` at its own depth ends it (not a
/// sleep in an argument list or a block's tail expression).
fn statement_end(code: &str) -> Option<usize> {
    let mut depth = 0i32;
    for (at, c) in code.char_indices() {
        match c {
            '{' | '(' | '[' => depth += 1,
            '}' | ')' | ']' => {
                depth -= 1;
                if depth < 0 {
                    return None;
                }
            }
            ';' if depth == 0 => return Some(at + 1),
            _ => {}
        }
    }
    None
}

/// Whether the statement at `at` has a `scenario:` comment on its line or just above it.
fn marked_scenario(file: &Source, at: usize) -> bool {
    let code_lines: Vec<&str> = file.code.split('\n').collect();
    let statement = file.code[..at].rfind([';', '{', '}']).map_or(0, |s| s + 1);
    let statement =
        statement + file.code[statement..at].len() - file.code[statement..at].trim_start().len();
    let (first, last) = (
        line_of(&file.code, statement) - 1,
        line_of(&file.code, at) - 1,
    );
    let mut lines: Vec<usize> = (first..=last).collect();
    let mut above = first;
    while above > 0
        && code_lines[above - 1].trim().is_empty()
        && !file.comments[above - 1].is_empty()
    {
        above -= 1;
        lines.push(above);
    }
    lines.iter().any(|&l| {
        let comment = file.comments[l].trim_start_matches('/').trim_start();
        comment.starts_with("scenario:")
    })
}

fn wall_clock_bounds(file: &Source) -> Vec<String> {
    let code = &file.code;
    let functions = functions(code);
    let std_instant = code.contains("std::time::Instant")
        || code
            .split(';')
            .any(|s| s.trim_start().starts_with("use std::time::") && s.contains("Instant"));
    let mut found = Vec::new();
    for at in assertions(code) {
        let Some(function) = functions.iter().rev().find(|f| f.body.contains(&at)) else {
            continue;
        };
        let body = &code[function.body.clone()];
        let condition = &code[at..at + block_len(&code[at..])];
        let condition = &condition[1..condition.len() - 1];
        let condition = split_top_level(condition, ",")[0];
        if !bounds_elapsed_from_above(condition, &elapsed_names(body)) {
            continue;
        }
        let wall_clock = if on_paused_clock(&functions, at) {
            std_instant && body.contains("Instant::now()") && !body.contains("tokio::time::Instant")
        } else {
            true
        };
        if wall_clock {
            let line = line_of(code, at);
            found.push(format!(
                "{}:{line}: an elapsed time bounded on the wall clock",
                file.path
            ));
        }
    }
    found
}

/// Where the argument list of each `assert!` (or `debug_assert!`) opens: the ones whose first
/// argument is a condition.
fn assertions(code: &str) -> Vec<usize> {
    ["assert", "debug_assert"]
        .iter()
        .flat_map(|name| {
            word_starts(code, name)
                .into_iter()
                .map(|at| (at, name.len()))
        })
        .filter_map(|(at, len)| {
            let rest = code[at + len..].trim_start().strip_prefix('!')?;
            let open = rest.trim_start();
            open.starts_with('(').then(|| code.len() - open.len())
        })
        .collect()
}

/// Names bound by `let NAME = ... .elapsed();` in `body`.
fn elapsed_names(body: &str) -> Vec<String> {
    word_starts(body, "let")
        .into_iter()
        .filter_map(|at| {
            let statement = &body[at + 3..];
            let statement = &statement[..statement_end(statement)? - 1];
            let (name, value) = statement.split_once('=')?;
            let name = name.split(':').next()?.trim();
            (value.trim().ends_with(".elapsed()") && name.chars().all(is_ident))
                .then(|| name.to_owned())
        })
        .collect()
}

/// Whether `condition` holds an elapsed time under a bound: `e < d`, `e <= d`, `d > e` or
/// `d >= e`, `e` a call of `elapsed()` or a name bound to one.
fn bounds_elapsed_from_above(condition: &str, names: &[String]) -> bool {
    let elapsed = |operand: &str| {
        let operand = operand.trim();
        operand.contains(".elapsed()") || names.iter().any(|n| n == operand)
    };
    split_top_level(condition, "&&")
        .into_iter()
        .flat_map(|part| split_top_level(part, "||"))
        .any(|part| {
            for (op, upper_on_left) in [("<=", true), (">=", false), ("<", true), (">", false)] {
                if let Some((left, right)) = part.split_once(op) {
                    if left.ends_with(['-', '=', '<', '>', ':'])
                        || right.starts_with(['<', '>', '='])
                    {
                        continue;
                    }
                    return if upper_on_left {
                        elapsed(left)
                    } else {
                        elapsed(right)
                    };
                }
            }
            false
        })
}

/// `text` split at each `separator` outside brackets.
fn split_top_level<'a>(text: &'a str, separator: &str) -> Vec<&'a str> {
    let mut parts = Vec::new();
    let (mut depth, mut start) = (0i32, 0);
    let mut at = 0;
    while at < text.len() {
        if !text.is_char_boundary(at) {
            at += 1;
            continue;
        }
        match text.as_bytes()[at] {
            b'{' | b'(' | b'[' => depth += 1,
            b'}' | b')' | b']' => depth -= 1,
            _ if depth == 0 && text[at..].starts_with(separator) => {
                parts.push(&text[start..at]);
                at += separator.len();
                start = at;
                continue;
            }
            _ => {}
        }
        at += 1;
    }
    parts.push(&text[start..]);
    parts
}

//! The layer rule of docs/design.md §4, checked on the source text:
//!
//! ```text
//! error, progress, spatial, stats  <  scene  <  kernel, optim  <  splat, trace  <  shade  <  io
//!                           <  eval  <  stages  <  cli (the binary's own module)
//! ```
//!
//! A library module may name (`crate::…`) only modules of its own layer's module or of a lower
//! layer; the library never names the binary's `cli`; and no two source files name each other,
//! directly or round a longer loop (`crate::a::b` or `super::b` paths, resolved to files). Doc
//! comments, comments and string literals are left out: a doc link to a higher layer is a
//! reader's pointer, not a dependency.
//!
//! Each test first shows that its check finds a planted violation, so it cannot pass by
//! matching nothing.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The layer of each top-level module of the library (`src/<name>.rs` or `src/<name>/`).
const LAYERS: [(&str, u32); 16] = [
    ("error", 0),
    ("progress", 0),
    ("spatial", 0),
    ("stats", 0),
    ("scene", 1),
    ("kernel", 2),
    ("optim", 2),
    ("splat", 3),
    ("trace", 3),
    ("shade", 4),
    ("io", 5),
    ("eval", 6),
    ("stages", 7),
    ("cli", 8),
    ("lib", 9),
    ("main", 9),
];

fn layer(module: &str) -> Option<u32> {
    LAYERS.iter().find(|(m, _)| *m == module).map(|&(_, l)| l)
}

/// The source without comments and string literals (char literals are kept: they hold no
/// `crate::`), so that only code is searched.
fn code_only(text: &str) -> String {
    let b = text.as_bytes();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < b.len() {
        if b[i..].starts_with(b"//") {
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
        } else if b[i..].starts_with(b"/*") {
            let mut depth = 0;
            while i < b.len() {
                if b[i..].starts_with(b"/*") {
                    depth += 1;
                    i += 2;
                } else if b[i..].starts_with(b"*/") {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    i += 1;
                }
            }
        } else if b[i] == b'"' || b[i..].starts_with(b"r\"") || b[i..].starts_with(b"r#") {
            // A string: plain ("…" with escapes) or raw (r"…", r#"…"#).
            let raw = b[i] == b'r';
            let mut hashes = 0;
            if raw {
                i += 1;
                while i < b.len() && b[i] == b'#' {
                    hashes += 1;
                    i += 1;
                }
                if i >= b.len() || b[i] != b'"' {
                    out.push('r');
                    continue;
                }
            }
            i += 1;
            while i < b.len() {
                if !raw && b[i] == b'\\' {
                    i += 2;
                } else if b[i] == b'"'
                    && b[i + 1..].len() >= hashes
                    && b[i + 1..i + 1 + hashes].iter().all(|&c| c == b'#')
                {
                    i += 1 + hashes;
                    break;
                } else {
                    i += 1;
                }
            }
            out.push_str("\"\"");
        } else {
            let c = text[i..].chars().next().expect("a char at a char boundary");
            out.push(c);
            i += c.len_utf8();
        }
    }
    out
}

/// A source file's module path (`["stages", "reconstruct", "run"]`; `mod.rs` is its folder).
fn module_path(src: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(src).expect("a file under src");
    let mut parts: Vec<String> = rel
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    let last = parts.pop().expect("a file name");
    let stem = last.trim_end_matches(".rs");
    if stem != "mod" {
        parts.push(stem.to_string());
    }
    parts
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.expect("a directory entry").path())
        .collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|e| e == "rs") {
            out.push(p);
        }
    }
}

/// Every `crate::a::b::…` path and every `super::…` path of `code` (in file `module`),
/// resolved to a module path as long as it names modules (the caller keeps the longest prefix
/// that is a file). `use a::{b, c}` groups are expanded one level.
fn named_paths(code: &str, module: &[String]) -> Vec<Vec<String>> {
    let ident = |c: char| c.is_alphanumeric() || c == '_';
    let mut found = Vec::new();
    let mut rest = code;
    while let Some(at) = rest.find(['c', 's']) {
        let before_ok = at == 0 || !rest[..at].chars().next_back().is_some_and(ident);
        let tail = &rest[at..];
        let (base, after) = if before_ok && tail.starts_with("crate::") {
            (Vec::new(), &tail["crate::".len()..])
        } else if before_ok && tail.starts_with("super::") {
            // A file's module is its path (`a/b.rs` is a::b, `a/mod.rs` is a); `super` is that
            // module's parent, once per `super::`.
            let mut m = module.to_vec();
            let mut t = tail;
            while let Some(r) = t.strip_prefix("super::") {
                m.pop();
                t = r;
            }
            (m, t)
        } else {
            rest = &rest[at + 1..];
            continue;
        };
        let segs: String = after
            .chars()
            .take_while(|&c| {
                ident(c) || c == ':' || c == '{' || c == '}' || c == ',' || c.is_whitespace()
            })
            .collect();
        let (head, group) = match segs.find('{') {
            Some(b) => (&segs[..b], segs[b + 1..].split('}').next()),
            None => (segs.as_str(), None),
        };
        let mut path = base.clone();
        path.extend(
            head.split("::")
                .map(str::trim)
                .filter(|s| !s.is_empty() && s.chars().all(ident))
                .map(String::from),
        );
        match group {
            Some(g) => {
                for item in g.split(',') {
                    let mut p = path.clone();
                    p.extend(
                        item.split("::")
                            .map(str::trim)
                            .filter(|s| !s.is_empty() && s.chars().all(ident) && *s != "self")
                            .map(String::from),
                    );
                    found.push(p);
                }
            }
            None => found.push(path),
        }
        rest = &rest[at + 1..];
    }
    found
}

struct Source {
    module: Vec<String>,
    file: PathBuf,
    code: String,
}

fn read_sources(src: &Path) -> Vec<Source> {
    let mut files = Vec::new();
    rust_files(src, &mut files);
    files
        .into_iter()
        .map(|file| {
            let text = std::fs::read_to_string(&file).expect("readable source");
            Source {
                module: module_path(src, &file),
                code: code_only(&text),
                file,
            }
        })
        .collect()
}

/// Module paths of the files, for resolving a named path to the file it lives in.
fn file_modules(sources: &[Source]) -> BTreeSet<Vec<String>> {
    sources.iter().map(|s| s.module.clone()).collect()
}

/// The longest prefix of `path` that is a file's module.
fn resolve(path: &[String], files: &BTreeSet<Vec<String>>) -> Option<Vec<String>> {
    (1..=path.len())
        .rev()
        .map(|n| path[..n].to_vec())
        .find(|p| files.contains(p))
}

/// Every layer violation: (file, the top-level module it names, why).
fn layer_violations(sources: &[Source]) -> Vec<String> {
    let mut bad = Vec::new();
    for s in sources {
        let top = s.module.first().map(String::as_str).unwrap_or("lib");
        let Some(own) = layer(top) else {
            bad.push(format!(
                "{}: module {top:?} has no layer in tests/layers.rs",
                s.file.display()
            ));
            continue;
        };
        let in_binary = top == "cli" || top == "main";
        for p in named_paths(&s.code, &s.module) {
            let Some(t) = p.first() else { continue };
            if t == top {
                continue;
            }
            if !in_binary && t == "cli" {
                bad.push(format!(
                    "{}: the library names the binary's cli",
                    s.file.display()
                ));
                continue;
            }
            match layer(t) {
                Some(l) if l > own || (l == own && !in_binary) => bad.push(format!(
                    "{}: {top} (layer {own}) names crate::{t} (layer {l})",
                    s.file.display()
                )),
                _ => {}
            }
        }
    }
    bad.sort();
    bad.dedup();
    bad
}

/// The loops of the file graph (each as the files round it), by depth-first search.
fn file_cycles(sources: &[Source]) -> Vec<Vec<String>> {
    let files = file_modules(sources);
    let mut edges: BTreeMap<Vec<String>, BTreeSet<Vec<String>>> = BTreeMap::new();
    for s in sources {
        let out = edges.entry(s.module.clone()).or_default();
        for p in named_paths(&s.code, &s.module) {
            if let Some(f) = resolve(&p, &files) {
                // A folder's mod.rs naming its own children, or a child naming its folder's
                // mod.rs re-exports, is structure, not a loop.
                if f != s.module && !f.starts_with(&s.module) && !s.module.starts_with(&f) {
                    out.insert(f);
                }
            }
        }
    }
    let mut cycles = Vec::new();
    let mut done = BTreeSet::new();
    for start in edges.keys() {
        let mut stack = vec![(start.clone(), vec![start.clone()])];
        while let Some((at, trail)) = stack.pop() {
            for next in edges.get(&at).into_iter().flatten() {
                if next == start {
                    let mut c: Vec<String> = trail.iter().map(|m| m.join("::")).collect();
                    let low = c.iter().min().cloned().expect("a non-empty loop");
                    let i = c.iter().position(|m| *m == low).expect("present");
                    c.rotate_left(i);
                    if done.insert(c.clone()) {
                        cycles.push(c);
                    }
                } else if !trail.contains(next) && trail.len() < 6 {
                    let mut t = trail.clone();
                    t.push(next.clone());
                    stack.push((next.clone(), t));
                }
            }
        }
    }
    cycles
}

fn src_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src")
}

fn source(module: &[&str], text: &str) -> Source {
    let module: Vec<String> = module.iter().map(|s| s.to_string()).collect();
    Source {
        file: PathBuf::from(format!("src/{}.rs", module.join("/"))),
        module,
        code: code_only(text),
    }
}

#[test]
fn the_checks_find_planted_violations() {
    // A lower layer naming a higher one, in a `use` and in an expression; the same in a comment
    // and a string is not code.
    let planted = [
        source(&["scene", "a"], "use crate::shade::brdf::f;\n"),
        source(&["trace", "b"], "fn g() { crate::io::read(); }\n"),
        source(
            &["kernel", "c"],
            "// crate::eval::x\nconst S: &str = \"crate::stages\";\n",
        ),
        source(&["eval", "d"], "use crate::cli::Args;\n"),
        source(&["splat", "e"], "use crate::{trace::X, scene::Y};\n"),
    ];
    let found = layer_violations(&planted);
    assert_eq!(found.len(), 4, "{found:#?}");
    assert!(found
        .iter()
        .any(|v| v.contains("scene/a.rs") && v.contains("crate::shade")));
    assert!(found
        .iter()
        .any(|v| v.contains("trace/b.rs") && v.contains("crate::io")));
    assert!(found
        .iter()
        .any(|v| v.contains("eval/d.rs") && v.contains("cli")));
    assert!(found
        .iter()
        .any(|v| v.contains("splat/e.rs") && v.contains("crate::trace")));
    // Two files naming each other, and a loop of three.
    let looped = [
        source(&["eval", "relight"], "use crate::eval::html;\n"),
        source(&["eval", "html"], "use crate::eval::relight::Report;\n"),
        source(&["io", "x"], "use super::y::A;\n"),
        source(&["io", "y"], "use crate::io::z::B;\n"),
        source(&["io", "z"], "use super::x::C;\n"),
    ];
    let cycles = file_cycles(&looped);
    assert_eq!(
        cycles,
        [
            vec!["eval::html".to_string(), "eval::relight".to_string()],
            vec!["io::x".into(), "io::y".into(), "io::z".into()],
        ]
    );
}

#[test]
fn every_library_module_names_only_lower_layers() {
    let sources = read_sources(&src_dir());
    assert!(sources.len() > 50, "the whole source tree is read");
    let bad = layer_violations(&sources);
    assert!(
        bad.is_empty(),
        "imports against the layers of docs/design.md §4:\n{}",
        bad.join("\n")
    );
}

#[test]
fn no_source_files_name_each_other() {
    let cycles = file_cycles(&read_sources(&src_dir()));
    assert!(
        cycles.is_empty(),
        "files that name each other (round a loop):\n{}",
        cycles
            .iter()
            .map(|c| c.join(" -> "))
            .collect::<Vec<_>>()
            .join("\n")
    );
}

//! No import circles in the crate: between its top-level modules (`camera`, `sweep`,
//! `render`, ...), and between the sibling files of one module (`conv/plan.rs`,
//! `conv/direct_grad.rs`, ...). A module refers to another by a `crate::` or `super::`
//! path in its code; a child's references to its own ancestors, and a module's to its own
//! children, are the tree and not edges. Tests (`tests.rs`, `tests_*.rs`, `*_tests.rs`)
//! are left out: they may use anything.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Module path of a source file: `src/camera/rolling.rs` is `camera::rolling`.
fn module_of(src: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(src).expect("under src");
    let mut parts: Vec<String> = rel
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    let last = parts.pop().unwrap_or_default();
    let stem = last.trim_end_matches(".rs");
    if stem != "mod" && stem != "lib" {
        parts.push(stem.to_string());
    }
    parts
}

fn files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).expect("read src").flatten() {
        let p = e.path();
        if p.is_dir() {
            files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

fn is_test(m: &[String]) -> bool {
    m.last()
        .is_some_and(|l| l == "tests" || l.starts_with("tests_") || l.ends_with("_tests"))
}

/// The module paths the code of `text` (in module `here`) refers to: `crate::a::b` and
/// `super::x` (resolved), each as far as two components; `#[cfg(test)]` blocks and
/// comments are left out.
fn references(here: &[String], text: &str) -> Vec<Vec<String>> {
    let code: String = text
        .split("#[cfg(test)]")
        .next()
        .unwrap_or_default()
        .lines()
        .map(|l| l.split("//").next().unwrap_or_default())
        .collect::<Vec<_>>()
        .join("\n");
    let ident = |s: &str| -> Vec<String> {
        s.split("::")
            .map(|p| {
                p.chars()
                    .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                    .collect::<String>()
            })
            .take_while(|p| {
                !p.is_empty() && p.chars().next().is_some_and(|c| c.is_ascii_lowercase())
            })
            .collect()
    };
    // `a::{b, c::d}` names `a::b` and `a::c` too.
    let group = |rest: &str, base: Vec<String>, out: &mut Vec<Vec<String>>| {
        let path = ident(rest);
        let after: String = rest
            .chars()
            .skip_while(|c| *c != '{' && *c != ';' && *c != '\n')
            .collect();
        let mut full = base.clone();
        full.extend(path.iter().cloned());
        let brace = rest.find('{');
        let plain_end = rest
            .find([';', '\n', ' ', ',', ')', '(', '<', '>', '.'])
            .unwrap_or(rest.len());
        if let (Some(b), true) = (brace, after.starts_with('{')) {
            if b < plain_end {
                let inner = &rest[b + 1..];
                let mut depth = 0;
                let mut end = inner.len();
                for (k, c) in inner.char_indices() {
                    match c {
                        '{' => depth += 1,
                        '}' if depth == 0 => {
                            end = k;
                            break;
                        }
                        '}' => depth -= 1,
                        _ => {}
                    }
                }
                for item in inner[..end].split(',') {
                    let mut p = full.clone();
                    p.extend(ident(item.trim()));
                    out.push(p);
                }
                return;
            }
        }
        out.push(full);
    };
    let mut out = Vec::new();
    for (i, _) in code.match_indices("crate::") {
        group(&code[i + 7..], Vec::new(), &mut out);
    }
    for (i, _) in code.match_indices("super::") {
        if code[..i].ends_with("::") {
            continue; // super::super:: is counted from its first
        }
        let mut base = here.to_vec();
        let mut rest = &code[i..];
        while let Some(r) = rest.strip_prefix("super::") {
            base.pop();
            rest = r;
        }
        group(rest, base, &mut out);
    }
    out
}

fn cycles(edges: &BTreeMap<String, BTreeSet<String>>) -> Vec<Vec<String>> {
    fn dfs(
        n: &str,
        edges: &BTreeMap<String, BTreeSet<String>>,
        stack: &mut Vec<String>,
        done: &mut BTreeSet<String>,
        found: &mut Vec<Vec<String>>,
    ) {
        if let Some(i) = stack.iter().position(|s| s == n) {
            found.push(stack[i..].to_vec());
            return;
        }
        if done.contains(n) {
            return;
        }
        stack.push(n.to_string());
        for m in edges.get(n).into_iter().flatten() {
            dfs(m, edges, stack, done, found);
        }
        stack.pop();
        done.insert(n.to_string());
    }
    let mut found = Vec::new();
    let mut done = BTreeSet::new();
    for n in edges.keys() {
        dfs(n, edges, &mut Vec::new(), &mut done, &mut found);
    }
    found
}

#[test]
fn no_module_imports_another_that_imports_it_back() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut all = Vec::new();
    files(&src, &mut all);
    let modules: BTreeSet<Vec<String>> = all.iter().map(|f| module_of(&src, f)).collect();
    // Modules declared under `#[cfg(test)]` are tests whatever their name.
    let mut test_only = BTreeSet::new();
    for f in &all {
        let here = module_of(&src, f);
        let text = std::fs::read_to_string(f).expect("read");
        let lines: Vec<&str> = text.lines().collect();
        for w in lines.windows(2) {
            if w[0].trim() == "#[cfg(test)]" {
                if let Some(name) = w[1]
                    .trim()
                    .strip_prefix("mod ")
                    .and_then(|r| r.strip_suffix(';'))
                {
                    let mut m = here.clone();
                    m.push(name.to_string());
                    test_only.insert(m);
                }
            }
        }
    }
    let is_test = |m: &[String]| is_test(m) || (1..=m.len()).any(|k| test_only.contains(&m[..k]));
    let mut top: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    let mut siblings: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for f in &all {
        let here = module_of(&src, f);
        if here.is_empty() || is_test(&here) {
            continue;
        }
        let text = std::fs::read_to_string(f).expect("read");
        for r in references(&here, &text) {
            let Some(first) = r.first() else { continue };
            if !modules.contains(&vec![first.clone()]) {
                continue; // an item of lib.rs, not a module
            }
            if *first != here[0] {
                top.entry(here[0].clone())
                    .or_default()
                    .insert(first.clone());
            } else if here.len() >= 2 && r.len() >= 2 && r[1] != here[1] {
                let to = r[..2].to_vec();
                if modules.contains(&to) && !is_test(&to) {
                    siblings
                        .entry(here[..2].join("::"))
                        .or_default()
                        .insert(to.join("::"));
                }
            }
        }
    }
    let mut found = cycles(&top);
    found.extend(cycles(&siblings));
    assert!(
        found.is_empty(),
        "import circles: {}",
        found
            .iter()
            .map(|c| format!("{} -> {}", c.join(" -> "), c[0]))
            .collect::<Vec<_>>()
            .join("; ")
    );
}

//! The results table: every check prints one markdown row and the whole table is kept in
//! `target/stability.md` (rows of other tests already in the file are kept, so a filtered
//! run updates only its own rows).

use std::path::PathBuf;
use std::sync::Mutex;

const HEADER: &str = "| case | check | worst error |\n|---|---|---|\n";
static LOCK: Mutex<()> = Mutex::new(());

/// Where the table is written: `$CARGO_TARGET_DIR/stability.md`, else the workspace's
/// `target/stability.md`.
pub fn table_path() -> PathBuf {
    match std::env::var_os("CARGO_TARGET_DIR") {
        Some(d) => PathBuf::from(d).join("stability.md"),
        None => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target/stability.md"),
    }
}

/// Formats a worst error: `0` exactly, else three significant digits.
pub fn fmt_err(v: f64) -> String {
    if v == 0.0 {
        "0".into()
    } else if v.is_finite() {
        format!("{v:.2e}")
    } else {
        format!("{v}")
    }
}

/// Prints `| case | check | worst |` and records it in the table file.
pub fn row(case: &str, check: &str, worst: f64) {
    row_text(case, check, &fmt_err(worst));
}

/// [`row`] with a worst-error cell given as text.
pub fn row_text(case: &str, check: &str, worst: &str) {
    let line = format!("| {case} | {check} | {worst} |");
    println!("{line}");
    let _guard = LOCK.lock().unwrap_or_else(|e| e.into_inner());
    let path = table_path();
    let old = std::fs::read_to_string(&path).unwrap_or_default();
    let key = |l: &str| l.split('|').take(3).collect::<Vec<_>>().join("|");
    let mut rows: Vec<String> = old
        .lines()
        .filter(|l| l.starts_with("| ") && !l.starts_with("| case |"))
        .map(str::to_string)
        .collect();
    match rows.iter_mut().find(|l| key(l) == key(&line)) {
        Some(slot) => *slot = line,
        None => rows.push(line),
    }
    let mut text = String::from(HEADER);
    rows.iter().for_each(|r| {
        text.push_str(r);
        text.push('\n');
    });
    if let Some(dir) = path.parent() {
        let _ = std::fs::create_dir_all(dir);
    }
    if let Err(e) = std::fs::write(&path, text) {
        eprintln!("cannot write {}: {e}", path.display());
    }
}

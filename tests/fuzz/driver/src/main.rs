//! A deterministic mutation fuzzer for stable Rust, running the targets of
//! `tests/fuzz/targets.rs` (the same functions as the cargo-fuzz binaries).
//!
//! `fuzz-driver SECONDS [TARGET...]` splits the time evenly over the targets (all by
//! default). Each target runs in a child process (`--child`), so that an abort (a huge
//! allocation, a stack overflow) is reported instead of ending the run. A child starts
//! from the seed corpus plus the saved regressions, and repeatedly mutates an input of its
//! pools (bit flips, interesting bytes, insertions, deletions, truncations, duplications,
//! splices, replaced number tokens, overwritten binary integers and floats) and runs it
//! under `catch_unwind`. One accepted input in eight joins the pool it mostly mutates;
//! an input whose error message has a new shape joins the other (a crude stand-in for
//! coverage). `FUZZ_DEBUG=1` prints each new error shape. Crashes are saved as `regressions/<target>/crash-<hash>`,
//! allocations above 256 MiB as `oom-<hash>` and inputs running over 10 s as
//! `hang-<hash>`; the same seeds give the same sequence of inputs.

#[path = "../../targets.rs"]
mod targets;

use std::alloc::{GlobalAlloc, Layout, System};
use std::collections::HashSet;
use std::io::{BufRead, BufReader};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering::Relaxed};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant};

/// Largest single allocation a small input may cause.
const ALLOC_LIMIT: usize = 256 << 20;
/// Longest time one input may run.
const HANG: Duration = Duration::from_secs(10);
/// Longest input produced.
const MAX_LEN: usize = 64 << 10;
/// Most inputs kept in the pool.
const MAX_POOL: usize = 2000;

// ---- Crash bookkeeping shared with the allocator, the panic hook and the watchdog -----

static LIMIT: AtomicUsize = AtomicUsize::new(usize::MAX);
static CURRENT: Mutex<Vec<u8>> = Mutex::new(Vec::new());
static TARGET: OnceLock<(String, PathBuf)> = OnceLock::new();
static PANIC: Mutex<Option<String>> = Mutex::new(None);
static BUSY_SINCE_MS: AtomicU64 = AtomicU64::new(0);

struct Guarded;

unsafe impl GlobalAlloc for Guarded {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        check_size(l.size());
        System.alloc(l)
    }
    unsafe fn alloc_zeroed(&self, l: Layout) -> *mut u8 {
        check_size(l.size());
        System.alloc_zeroed(l)
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, new: usize) -> *mut u8 {
        check_size(new);
        System.realloc(p, l, new)
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        System.dealloc(p, l)
    }
}

#[global_allocator]
static ALLOC: Guarded = Guarded;

fn check_size(size: usize) {
    if size > LIMIT.load(Relaxed) {
        LIMIT.store(usize::MAX, Relaxed);
        die("oom", &format!("allocation of {size} bytes"));
    }
}

fn fnv(data: &[u8]) -> u64 {
    data.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x100_0000_01b3))
}

/// Saves `data` as `regressions/<target>/<kind>-<hash>` and returns the path.
fn save(kind: &str, data: &[u8]) -> Option<PathBuf> {
    let (target, root) = TARGET.get()?;
    let dir = root.join(target);
    std::fs::create_dir_all(&dir).ok()?;
    let path = dir.join(format!("{kind}-{:016x}", fnv(data)));
    std::fs::write(&path, data).ok()?;
    Some(path)
}

/// Saves the current input and aborts (for what cannot be unwound).
fn die(kind: &str, what: &str) -> ! {
    let data = CURRENT.try_lock().map(|d| d.clone()).unwrap_or_default();
    let path = save(kind, &data);
    eprintln!("{} {kind}: {what}; input saved as {path:?}", TARGET.get().map_or("?", |t| t.0.as_str()));
    std::process::abort()
}

fn now_ms() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64)
}

// ---- Mutations ----------------------------------------------------------------------

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        if n == 0 { 0 } else { (self.next() % n as u64) as usize }
    }
}

const BYTES: &[u8] = b"\x00\xff\x7f\x80\xc3\x0009-.e+\n\r\t ,:\"'[]{}()#_/\\";
const TOKENS: &[&str] = &[
    "0", "-0", "1", "-1", "2", "3", "17", "255", "65535", "4294967295", "4294967296", "2147483648", "-2147483649",
    "18446744073709551615", "18446744073709551616", "99999999999999999999999", "1e308", "-1e308", "1e309", "5e-324",
    "1e-320", "nan", "NaN", "inf", "-inf", "Infinity", "0.5", "1.5", "3.14159", "1e6", "-1e-6", "0x10", "",
    "null", "true", "false", "[]", "{}", "\"\"", "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]", "PINHOLE", "OPENCV",
    "SIMPLE_PINHOLE", "FULL_OPENCV", "FOV", "\u{feff}", "\u{1F600}", "#", "\n", "(", ")", ",", "'<f8'", "'<f4'",
    "True", "F32", "F16", "I64", "\"kernel\"", "\"channels\"",
];
const INTS: &[u64] = &[0, 1, 2, 3, 4, 7, 8, 255, 256, 0x7fff_ffff, 0x8000_0000, 0xffff_ffff, 1 << 32, 1 << 40, 1 << 62, u64::MAX, u64::MAX - 1];
const FLOATS: &[f64] = &[0.0, -0.0, 1.0, -1.0, 0.5, 1e-300, 5e-324, 1e300, f64::MAX, f64::INFINITY, f64::NEG_INFINITY, f64::NAN, 1e7, 1e-7];

/// Byte ranges of ASCII number-like tokens.
fn numbers(d: &[u8]) -> Vec<(usize, usize)> {
    let num = |b: u8| b.is_ascii_digit() || b"+-.eE".contains(&b);
    let mut out = Vec::new();
    let mut i = 0;
    while i < d.len() {
        if d[i].is_ascii_digit() {
            let mut s = i;
            while s > 0 && num(d[s - 1]) {
                s -= 1;
            }
            let mut e = i;
            while e < d.len() && num(d[e]) {
                e += 1;
            }
            out.push((s, e));
            i = e;
        } else {
            i += 1;
        }
    }
    out
}

fn mutate(base: &[u8], pool: &[Vec<u8>], r: &mut Rng) -> Vec<u8> {
    let mut d = base.to_vec();
    for _ in 0..1 + r.below(4) {
        let n = d.len();
        match r.below(12) {
            0 if n > 0 => {
                let i = r.below(n);
                d[i] ^= 1 << r.below(8);
            }
            1 if n > 0 => {
                let i = r.below(n);
                d[i] = if r.below(4) == 0 { r.next() as u8 } else { BYTES[r.below(BYTES.len())] };
            }
            2 => {
                let i = r.below(n + 1);
                let k = 1 + r.below(8);
                let ins: Vec<u8> = (0..k).map(|_| r.next() as u8).collect();
                d.splice(i..i, ins);
            }
            3 => {
                let i = r.below(n + 1);
                let t = TOKENS[r.below(TOKENS.len())].as_bytes().to_vec();
                d.splice(i..i, t);
            }
            4 if n > 0 => {
                let i = r.below(n);
                let k = 1 + r.below((n - i).min(64));
                d.drain(i..i + k);
            }
            5 => d.truncate(r.below(n + 1)),
            6 if n > 0 => {
                let i = r.below(n);
                let k = 1 + r.below((n - i).min(256));
                let chunk = d[i..i + k].to_vec();
                let at = r.below(n + 1);
                d.splice(at..at, chunk);
            }
            7 if !pool.is_empty() => {
                let other = &pool[r.below(pool.len())];
                let (a, b) = (r.below(n + 1), r.below(other.len() + 1));
                d.truncate(a);
                d.extend_from_slice(&other[b..]);
            }
            8 | 9 => {
                let nums = numbers(&d);
                if !nums.is_empty() {
                    let (s, e) = nums[r.below(nums.len())];
                    let t = TOKENS[r.below(TOKENS.len())].as_bytes().to_vec();
                    d.splice(s..e, t);
                }
            }
            10 if n >= 8 => {
                let v = INTS[r.below(INTS.len())];
                let i = if r.below(2) == 0 { r.below(n / 4) * 4 } else { r.below(n - 7) };
                let width = [4usize, 8][r.below(2)].min(n - i);
                d[i..i + width].copy_from_slice(&v.to_le_bytes()[..width]);
            }
            11 if n >= 8 => {
                let v = FLOATS[r.below(FLOATS.len())];
                let i = if r.below(2) == 0 { r.below(n / 8) * 8 } else { r.below(n - 7) };
                d[i..i + 8].copy_from_slice(&v.to_le_bytes());
            }
            _ => {}
        }
    }
    d.truncate(MAX_LEN);
    d
}

/// The shape of an error message: its plain lowercase words (paths, numbers, quoted and
/// other input-dependent tokens dropped), for novelty.
fn shape_of(msg: &str) -> String {
    let words = msg.split_whitespace().map(|w| w.trim_end_matches([',', ':', ';', ')']));
    let plain = words.filter(|w| !w.is_empty() && w.chars().all(|c| c.is_ascii_lowercase() || c == '-'));
    plain.take(12).collect::<Vec<_>>().join(" ")
}

// ---- Child: fuzz one target ---------------------------------------------------------

fn child(target: &str, budget: Duration, seed: u64, root: &Path, corpus: Option<&Path>) {
    let _ = TARGET.set((target.to_string(), root.to_path_buf()));
    std::panic::set_hook(Box::new(|info| {
        let loc = info.location().map(|l| format!("{}:{}", l.file(), l.line())).unwrap_or_default();
        let text = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_default();
        *PANIC.lock().unwrap_or_else(|e| e.into_inner()) = Some(format!("{text} at {loc}"));
    }));
    std::thread::spawn(|| loop {
        std::thread::sleep(Duration::from_millis(250));
        let since = BUSY_SINCE_MS.load(Relaxed);
        if since != 0 && now_ms().saturating_sub(since) > HANG.as_millis() as u64 {
            die("hang", &format!("an input ran over {HANG:?}"));
        }
    });
    let fx = targets::Fixture::new();
    println!("FIXTURE {}", fx.dir.display()); // the parent removes it if this child aborts
    let pool = targets::seeds(target, &fx);
    if let Some(dir) = corpus.map(|c| c.join(target)) {
        let _ = std::fs::create_dir_all(&dir);
        for s in &pool {
            let _ = std::fs::write(dir.join(format!("seed-{:016x}", fnv(s))), s);
        }
    }
    let seeds = pool.len();
    // A restarted child (seed > 0) leaves out the regressions: one of them may be what
    // made the previous child abort.
    let kept = if seed == 0 { targets::regressions(root, target) } else { Vec::new() };
    let mut odd: Vec<Vec<u8>> = kept.into_iter().filter_map(|p| std::fs::read(p).ok()).collect();
    let debug = std::env::var_os("FUZZ_DEBUG").is_some();
    let mut seen: HashSet<String> = HashSet::new();
    let mut crashes: HashSet<String> = HashSet::new();
    let mut r = Rng(fnv(target.as_bytes()) ^ seed.wrapping_mul(0x2545_F491_4F6C_DD1D));
    let (start, mut execs, mut oks) = (Instant::now(), 0u64, 0u64);
    let mut queue: Vec<Vec<u8>> = pool.iter().chain(&odd).cloned().collect(); // run first
    let mut good = pool;
    LIMIT.store(ALLOC_LIMIT, Relaxed);
    while start.elapsed() < budget {
        let input = match queue.pop() {
            Some(q) => q,
            None => {
                // Mostly from accepted inputs, sometimes from ones with an unusual error.
                let from = if odd.is_empty() || r.below(4) != 0 { &good } else { &odd };
                mutate(&from[r.below(from.len())], from, &mut r)
            }
        };
        CURRENT.lock().unwrap_or_else(|e| e.into_inner()).clone_from(&input);
        BUSY_SINCE_MS.store(now_ms(), Relaxed);
        let result = catch_unwind(AssertUnwindSafe(|| targets::run(target, &input, &fx)));
        BUSY_SINCE_MS.store(0, Relaxed);
        execs += 1;
        if execs % 1024 == 0 {
            println!("EXECS {execs}"); // so that the parent can count the executions of a child that aborts
        }
        match result {
            Err(_) => {
                let what = PANIC.lock().unwrap_or_else(|e| e.into_inner()).take().unwrap_or_default();
                if crashes.insert(what.clone()) {
                    let path = save("crash", &input);
                    println!("CRASH {target}: {what}; input saved as {path:?}");
                }
            }
            Ok(res) => {
                let ok = res.is_ok();
                oks += ok as u64;
                let key = res.err().map_or("ok".to_string(), |e| shape_of(&e));
                if debug && !ok && !seen.contains(&key) {
                    eprintln!("new error kind: {key}");
                }
                // Accepted inputs (some) and inputs with a new kind of error join the pool.
                let keep = if ok { r.below(8) == 0 } else { seen.insert(key) };
                if keep {
                    let (list, cap) = if ok { (&mut good, MAX_POOL / 2) } else { (&mut odd, MAX_POOL / 2) };
                    if list.len() < cap {
                        list.push(input);
                    } else {
                        let floor = if ok { seeds } else { 0 };
                        let i = floor + r.below(cap - floor);
                        list[i] = input;
                    }
                }
            }
        }
    }
    LIMIT.store(usize::MAX, Relaxed);
    println!("RESULT {target} {execs} {} {oks} {}", crashes.len(), seen.len());
}

// ---- Parent: one child per target ---------------------------------------------------

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let here = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let root = here.join("regressions");
    let corpus = here.join("corpus");
    if args.get(1).map(String::as_str) == Some("--child") {
        let ms: u64 = args[3].parse().expect("budget");
        let seed: u64 = args[4].parse().expect("seed");
        child(&args[2], Duration::from_millis(ms), seed, &root, Some(&corpus));
        return;
    }
    let secs: f64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or_else(|| {
        eprintln!("usage: fuzz-driver SECONDS [TARGET...]   (targets: {})", targets::TARGETS.join(", "));
        std::process::exit(2)
    });
    let chosen: Vec<&str> = if args.len() > 2 {
        args[2..].iter().map(String::as_str).collect()
    } else {
        targets::TARGETS.to_vec()
    };
    let exe = std::env::current_exe().expect("own path");
    let per = Duration::from_secs_f64(secs / chosen.len() as f64);
    let (mut total, mut bad) = (0u64, 0usize);
    println!("| target | executions | crashes (unique) | accepted | error kinds |\n|---|---|---|---|---|");
    for t in &chosen {
        let (start, mut execs, mut crashes, mut attempt, mut extra) = (Instant::now(), 0u64, 0usize, 0u64, String::new());
        while start.elapsed() + Duration::from_millis(200) < per {
            let left = per - start.elapsed();
            let mut c = Command::new(&exe)
                .args(["--child", t, &left.as_millis().to_string(), &attempt.to_string()])
                .stdout(Stdio::piped())
                .spawn()
                .expect("spawn a child");
            let out = c.stdout.take().expect("child stdout");
            let (mut partial, mut fixture) = (0u64, None);
            for line in BufReader::new(out).lines().map_while(Result::ok) {
                if let Some(dir) = line.strip_prefix("FIXTURE ") {
                    fixture = Some(PathBuf::from(dir));
                } else if let Some(n) = line.strip_prefix("EXECS ") {
                    partial = n.parse().unwrap_or(partial);
                } else if let Some(rest) = line.strip_prefix("RESULT ") {
                    partial = 0;
                    let f: Vec<&str> = rest.split_whitespace().collect();
                    execs += f.get(1).and_then(|v| v.parse::<u64>().ok()).unwrap_or(0);
                    crashes += f.get(2).and_then(|v| v.parse::<usize>().ok()).unwrap_or(0);
                    extra = format!("{} | {}", f.get(3).unwrap_or(&"?"), f.get(4).unwrap_or(&"?"));
                } else {
                    eprintln!("{line}");
                }
            }
            let status = c.wait().expect("wait for the child");
            if let Some(dir) = fixture {
                let _ = std::fs::remove_dir_all(dir);
            }
            execs += partial;
            if !status.success() {
                crashes += 1; // an abort: the child printed and saved its input
                eprintln!("{t}: child ended with {status}; restarting with another seed");
            }
            attempt += 1;
        }
        println!("| {t} | {execs} | {crashes} | {extra} |");
        total += execs;
        bad += crashes;
    }
    println!("total: {total} executions, {bad} crashes; regressions in {}", root.display());
    if bad > 0 {
        std::process::exit(1);
    }
}

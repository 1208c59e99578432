//! Replays the inputs that once crashed (or hung) a fuzz target, kept under
//! `tests/fuzz/regressions/<target>/`, through the same target functions the fuzzers run
//! (`tests/fuzz/targets.rs`): each must now end in `Ok` or a clear error, quickly. Also
//! checks that every seed of the fuzzers' corpus is valid, so the fuzzers start deep in
//! the readers rather than at their first error.

#[path = "../../tests/fuzz/targets.rs"]
mod targets;

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;
use std::time::{Duration, Instant};
use targets::{Fixture, TARGETS};

/// Longest accepted time for one input.
const MAX_TIME: Duration = Duration::from_secs(5);

fn regressions_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/fuzz/regressions")
}

#[test]
fn regressions_give_errors_not_panics() {
    let fx = Fixture::new();
    let root = regressions_root();
    let mut replayed = 0;
    let mut failures = Vec::new();
    for name in TARGETS {
        for path in targets::regressions(&root, name) {
            let data = std::fs::read(&path).expect("read a regression input");
            let start = Instant::now();
            let result = catch_unwind(AssertUnwindSafe(|| targets::run(name, &data, &fx)));
            let took = start.elapsed();
            replayed += 1;
            match result {
                Err(_) => failures.push(format!("{name}: {} panics", path.display())),
                Ok(_) if took > MAX_TIME => {
                    failures.push(format!("{name}: {} took {took:?}", path.display()))
                }
                Ok(r) => println!(
                    "{name}: {}: {}",
                    path.file_name().unwrap_or_default().to_string_lossy(),
                    r.err().unwrap_or("ok".into())
                ),
            }
        }
    }
    println!("{replayed} regression inputs replayed");
    assert!(failures.is_empty(), "{failures:#?}");
}

#[test]
fn every_seed_is_valid() {
    let fx = Fixture::new();
    for name in TARGETS {
        let seeds = targets::seeds(name, &fx);
        assert!(!seeds.is_empty(), "{name}: no seeds");
        for (i, s) in seeds.iter().enumerate() {
            if let Err(e) = targets::run(name, s, &fx) {
                panic!("{name}: seed {i} is rejected: {e}");
            }
        }
    }
}

/// The weights loader refuses, before allocating, a config that needs more parameters
/// than the file holds; that relies on `Config::parameters` being exact.
#[test]
fn parameter_count_is_exact() {
    use deepstereo_core::config::Config;
    for cfg in Config::PRESETS.iter().filter_map(|n| Config::preset(n)) {
        let t = deepstereo_core::weights::init(&cfg, &candle_core::Device::Cpu).expect("init");
        let n: usize = deepstereo_core::weights::named_vars(&t.varmap)
            .iter()
            .map(|(_, v)| v.as_tensor().elem_count())
            .sum();
        assert_eq!(cfg.parameters(), n, "{}", cfg.name);
    }
}

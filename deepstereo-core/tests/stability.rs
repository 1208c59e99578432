//! Numerical stability on stiff and extreme cases (issue 7): geometry and plane sweeps,
//! the network and reduced precision (the optimizers' cases are deepstereo-train's
//! `tests/stability_optim.rs`). Every check prints one markdown row
//! `| case | check | worst error |`; the whole table is written to
//! `target/stability.md`. Reproduce with
//! `cargo test --release -p deepstereo-core --test stability -- --nocapture --test-threads 1`
//! and `cargo test --release -p deepstereo-train --test stability_optim -- --nocapture`.

#[path = "stability/fixtures.rs"]
mod fixtures;
#[path = "stability/geometry.rs"]
mod geometry;
#[path = "stability/network.rs"]
mod network;
#[path = "stability/table.rs"]
mod table;

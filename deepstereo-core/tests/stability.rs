//! Numerical stability on stiff and extreme cases (issue 7): geometry and plane sweeps,
//! the network, reduced precision and the optimizers. Every check prints one markdown
//! row `| case | check | worst error |`; the whole table is written to
//! `target/stability.md`. Reproduce with
//! `cargo test --release -p deepstereo-core --test stability -- --nocapture --test-threads 1`.

#[path = "stability/geometry.rs"]
mod geometry;
#[path = "stability/network.rs"]
mod network;
#[path = "stability/table.rs"]
mod table;
#[path = "stability/training.rs"]
mod training;

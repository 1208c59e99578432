//! Helpers only the commands use: cameras as JSON ([`camera_json`]), running COLMAP
//! ([`colmap_run`]), videos ([`video`]), output directories that appear whole
//! ([`outdir`]), and the process's signal handler ([`interrupt`]).

pub mod camera_json;
pub mod colmap_run;
pub mod interrupt;
pub mod outdir;
pub mod video;

//! DeepStereo training, evaluation and the `deepstereo` command line.

pub mod cmd;

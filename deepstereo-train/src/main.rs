//! The `deepstereo` command-line tool. Everything lives in the library; this only parses
//! arguments, runs the command, and turns errors into a message and a non-zero exit.

use clap::Parser;

fn main() {
    deepstereo_train::alloc::tune_allocator();
    let cli = deepstereo_train::cmd::Cli::parse();
    if let Err(e) = deepstereo_train::cmd::support::interrupt::install() {
        eprintln!("warning: no handler for Ctrl-C: {e}");
    }
    if let Err(e) = deepstereo_train::cmd::run(cli) {
        eprintln!("error: {e}");
        for cause in e.chain().skip(1) {
            eprintln!("  caused by: {cause}");
        }
        std::process::exit(1);
    }
}

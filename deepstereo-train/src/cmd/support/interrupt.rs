//! SIGINT and SIGTERM (and SIGHUP): one handler for the whole process, installed by
//! [`install`] before a command runs.
//!
//! - A command that can stop cleanly (`train`, `tune`) asks for [`graceful`]: the first
//!   signal sets its flag, and it saves what it has and exits by itself.
//! - Otherwise, and at a second signal, the handler removes every staging directory and
//!   temporary file the process is writing ([`crate::cmd::support::outdir::remove_pending`]) and exits
//!   with status 130, leaving the outputs as they were before the run.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};

/// Exit status after an interruption (128 + SIGINT, as shells report Ctrl-C).
pub const EXIT_INTERRUPTED: i32 = 130;

/// The flag of a command that stops by itself, once it asked for one.
static GRACEFUL: OnceLock<Arc<AtomicBool>> = OnceLock::new();

/// Installs the process's handler; an error only if another handler was installed first.
pub fn install() -> Result<(), ctrlc::Error> {
    ctrlc::set_handler(on_signal)
}

fn on_signal() {
    if let Some(flag) = GRACEFUL.get() {
        if !flag.swap(true, Ordering::SeqCst) {
            eprintln!("\ninterrupted: finishing the current step and saving (again to abort)");
            return;
        }
    }
    crate::cmd::support::outdir::remove_pending();
    eprintln!("\ninterrupted: partial outputs removed");
    std::process::exit(EXIT_INTERRUPTED);
}

/// The flag the first signal sets from now on, instead of ending the process: the caller
/// polls it and stops cleanly. Every call returns the same flag.
pub fn graceful() -> Arc<AtomicBool> {
    GRACEFUL
        .get_or_init(|| Arc::new(AtomicBool::new(false)))
        .clone()
}

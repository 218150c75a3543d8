//! The `scanloc` command: the process around the library's command line
//! ([`scanloc::cli`], which parses the arguments, calls the library and
//! maps errors to exit codes): logging, SIGPIPE, the allocator.

use std::io::IsTerminal;
use std::process::ExitCode;

fn main() -> ExitCode {
    restore_default_sigpipe();
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env(scanloc::env_vars::SCANLOC_LOG)
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .init();
    let styled = std::io::stderr().is_terminal();
    scanloc::cli::main_with(
        std::env::args_os(),
        &mut std::io::stdout(),
        &mut std::io::stderr(),
        styled,
    )
}

/// Lets a closed stdout end the process quietly, for every command at once
/// (`scanloc check … | head`): Rust ignores SIGPIPE, so each print to a
/// closed pipe would fail, and `println!` panics on that failure. With the
/// default action the process ends the way `cat` or `grep` do. Outputs to
/// files are unaffected (they are written to temporary files and renamed),
/// and the registry survives being stopped at any point.
fn restore_default_sigpipe() {
    #[cfg(unix)]
    // SAFETY: called first thing in `main`, before any other thread exists;
    // setting a signal's disposition to its default has no other effect.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// mimalloc instead of glibc's allocator: the CNN's tensors are allocated
/// and freed at every layer, and glibc returns that memory to the OS and
/// faults it back in each time (measured: a third slower training).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

//! `patchwork`: the daemon and its command line (the commands are in `cli/`).

mod cli;

use clap::Parser;
use std::process::ExitCode;

#[cfg(feature = "jemalloc")]
#[global_allocator]
static ALLOCATOR: patchwork::engine::Jemalloc = patchwork::engine::Jemalloc;

fn main() -> ExitCode {
    // Process-wide settings first, before any thread exists to see them change.
    patchwork::tune_allocator();
    // Two TLS crypto providers are linked: ring, which the gRPC and HTTP servers and the CLI's
    // client use, and aws-lc-rs, which the object store's HTTP client brings and uses by name.
    // rustls then cannot pick the process default itself, and must be told.
    let _ = rustls::crypto::ring::default_provider().install_default();
    quiet_vulkan_layers();
    let args = cli::Cli::parse();
    if !matches!(args.cmd, cli::Cmd::Serve(_)) {
        die_on_closed_pipe();
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime");
    let result = rt.block_on(cli::run(args));
    // Work still running on blocking threads (an ingest, a query past its deadline) is not
    // waited for: every commit is atomic, so stopping now is as safe as a crash.
    rt.shutdown_timeout(std::time::Duration::from_millis(500));
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("patchwork: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Turns off Mesa's device-select Vulkan layer, which the loader adds to every instance. To
/// pick a default device it connects to a Wayland display, and on a server without one that
/// prints an error to stderr at every start; the GPU probe ranks adapters itself. A value set
/// by the user stands.
fn quiet_vulkan_layers() {
    if std::env::var_os("NODEVICE_SELECT").is_none() {
        // SAFETY: called first thing in main, before the runtime or anything else starts a
        // thread that could read the environment at the same time.
        unsafe { std::env::set_var("NODEVICE_SELECT", "1") };
    }
}

/// A command whose output goes to a pipe closed early (`patchwork surveys | head -1`) ends
/// there, quietly, with the status a shell expects of it (141): Rust ignores SIGPIPE, so
/// that every print would otherwise fail with EPIPE and `println!` panic. Not for `serve`,
/// whose sockets' peers may go at any moment and must not take the daemon with them.
fn die_on_closed_pipe() {
    // SAFETY: restores the default action for one signal, before any thread is started.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

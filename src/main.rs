//! The `sisfilt` binary: parses the command line, runs the command, reports errors (docs/theory.md §13).

#![forbid(unsafe_code)]

use std::process::ExitCode;

use clap::Parser;
use clap::error::ErrorKind;
use sisfilt::messages;

mod app;

/// Exit code of a run stopped by SIGINT, SIGTERM or SIGHUP (the shell's 128 + SIGINT).
const INTERRUPTED: i32 = 130;

fn main() -> ExitCode {
    // Ctrl-C or a kill: remove the temporary output files and leave the previous outputs
    // as they were. The lock returned is held until the process is gone, so nothing more is
    // committed in the meantime.
    let _ = ctrlc::set_handler(|| {
        let _guard = sisfilt::io::remove_pending_files();
        std::process::exit(INTERRUPTED);
    });
    let cli = match app::Cli::try_parse() {
        Ok(cli) => cli,
        // --help, --version, and the help shown when no command is given.
        Err(e)
            if !e.use_stderr()
                || e.kind() == ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand =>
        {
            e.exit()
        }
        Err(e) => {
            messages::error(usage_error_line(&e));
            return ExitCode::from(u8::try_from(e.exit_code()).unwrap_or(2));
        }
    };
    messages::set_verbosity(cli.verbosity());
    let started = std::time::Instant::now();
    match app::run(cli.command) {
        Ok(()) => {
            messages::info(format!("done in {:.3} s", started.elapsed().as_secs_f64()));
            ExitCode::SUCCESS
        }
        Err(err) => {
            let broken_pipe = err.chain().any(|c| {
                c.downcast_ref::<std::io::Error>()
                    .is_some_and(|e| e.kind() == std::io::ErrorKind::BrokenPipe)
                    || matches!(c.downcast_ref::<sisfilt::Error>(),
                        Some(sisfilt::Error::Io { err, .. }) if err.kind() == std::io::ErrorKind::BrokenPipe)
            });
            if broken_pipe {
                return ExitCode::SUCCESS;
            }
            messages::error(format!("{err:#}"));
            let code = err
                .chain()
                .find_map(|c| c.downcast_ref::<sisfilt::Error>())
                .map_or(1, sisfilt::Error::exit_code);
            ExitCode::from(code)
        }
    }
}

/// A command-line error as one line (docs/theory.md §13): clap's message and its tips, without the usage
/// block that clap prints below them.
fn usage_error_line(e: &clap::Error) -> String {
    let text = e.to_string();
    let mut line = String::new();
    for part in text
        .lines()
        .map(str::trim)
        .take_while(|l| !l.starts_with("Usage:") && !l.starts_with("For more information"))
        .filter(|l| !l.is_empty())
    {
        if !line.is_empty() {
            line.push_str(if line.ends_with(':') { " " } else { "; " });
        }
        line.push_str(part.strip_prefix("error: ").unwrap_or(part));
    }
    line + " (see --help)"
}

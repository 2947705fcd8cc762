//! `sisfilt man [COMMAND…]`: the man pages, in roff.

use anyhow::{Context, Result};

use sisfilt::error::Error;

use super::print_stdout;

/// `sisfilt man [COMMAND…]`: the man page (roff) of `sisfilt` or of one of its commands
/// (`sisfilt man plot series` is the page `sisfilt-plot-series(1)`).
pub fn run(path: &[String]) -> Result<()> {
    let mut cmd = <super::Cli as clap::CommandFactory>::command();
    // Building propagates the global options (--quiet, --verbose) into every command.
    cmd.build();
    let mut name = "sisfilt".to_string();
    for word in path {
        let Some(sub) = cmd.find_subcommand(word).cloned() else {
            let known: Vec<&str> = cmd
                .get_subcommands()
                .map(clap::Command::get_name)
                .filter(|n| *n != "help")
                .collect();
            return Err(Error::Usage(format!(
                "man: `{name}` has no command `{word}`; expected one of: {}",
                known.join(", ")
            ))
            .into());
        };
        name = format!("{name}-{word}");
        cmd = sub;
    }
    let cmd = cmd.name(name).version(env!("CARGO_PKG_VERSION"));
    let mut page = Vec::new();
    clap_mangen::Man::new(cmd)
        .render(&mut page)
        .context("rendering the man page")?;
    print_stdout(&page)
}

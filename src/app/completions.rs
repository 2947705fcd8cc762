//! `sisfilt completions SHELL`: a shell completion script.

use anyhow::Result;

use super::print_stdout;

/// `sisfilt completions SHELL`: the completion script, generated from the clap definition.
pub fn run(shell: clap_complete::Shell) -> Result<()> {
    let mut cmd = <super::Cli as clap::CommandFactory>::command();
    let mut script = Vec::new();
    clap_complete::generate(shell, &mut cmd, "sisfilt", &mut script);
    print_stdout(&script)
}

//! The files one command reads and writes, checked together before any work starts: an output
//! must never be one of the inputs (writing it would destroy what is being read), and at most
//! one input can read standard input.
//!
//! Files are compared, not their names: `m.csv`, `./sub/../m.csv` and a symbolic link to it are
//! the same file. An existing path is known by its device and inode (its canonical path off
//! Unix); an output that does not exist yet by the canonical path of its folder and its name.

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// A file a command reads or writes, and what names it on the command line (`--meas`, `the
/// config`, …), for the message.
#[derive(Clone, Copy, Debug)]
pub struct Role<'a> {
    pub what: &'a str,
    pub path: &'a Path,
}

impl<'a> Role<'a> {
    pub fn new(what: &'a str, path: &'a Path) -> Self {
        Role { what, path }
    }

    fn is_stdio(&self) -> bool {
        self.path.as_os_str() == "-"
    }
}

/// The folder that holds `path`: its parent, or `.` for a bare file name.
pub fn folder_of(path: &Path) -> &Path {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    }
}

/// What a path is on disk, for comparing two paths.
#[derive(PartialEq, Eq, Debug)]
enum Identity {
    #[cfg(unix)]
    Inode {
        dev: u64,
        ino: u64,
    },
    Path(PathBuf),
}

/// The identity of `path`: the file it names (through symbolic links) when it exists, else
/// its would-be canonical path; `None` when neither can be known (its folder is missing too:
/// then it cannot be an existing input, and creating it fails later with its own message).
fn identity(path: &Path) -> Option<Identity> {
    if let Ok(meta) = std::fs::metadata(path) {
        return existing_identity(path, &meta);
    }
    let name = path.file_name()?;
    std::fs::canonicalize(folder_of(path))
        .ok()
        .map(|d| Identity::Path(d.join(name)))
}

#[cfg(unix)]
fn existing_identity(_: &Path, meta: &std::fs::Metadata) -> Option<Identity> {
    use std::os::unix::fs::MetadataExt;
    Some(Identity::Inode {
        dev: meta.dev(),
        ino: meta.ino(),
    })
}

#[cfg(not(unix))]
fn existing_identity(path: &Path, _: &std::fs::Metadata) -> Option<Identity> {
    std::fs::canonicalize(path).ok().map(Identity::Path)
}

/// Whether writing `path` could change a file: an existing regular file, or a path that does
/// not exist yet. Devices and pipes (`/dev/null`, a FIFO) are written in place and keep
/// nothing to destroy.
fn holds_data(path: &Path) -> bool {
    std::fs::metadata(path).map_or(true, |m| m.is_file())
}

/// Refuses (as bad input) a run whose outputs include one of its inputs, or whose inputs read
/// standard input more than once. Inputs that do not exist are left to the reader's own
/// message.
pub fn check_files(inputs: &[Role], outputs: &[Role]) -> Result<()> {
    let stdin: Vec<&Role> = inputs.iter().filter(|r| r.is_stdio()).collect();
    if let [first, second, ..] = stdin.as_slice() {
        return Err(Error::Usage(format!(
            "{} and {} cannot both read standard input (`-`); give one of them a file",
            first.what, second.what
        )));
    }
    let known: Vec<(Identity, &Role)> = inputs
        .iter()
        .filter(|r| !r.is_stdio())
        .filter_map(|r| {
            let meta = std::fs::metadata(r.path).ok()?;
            existing_identity(r.path, &meta).map(|id| (id, r))
        })
        .collect();
    for out in outputs
        .iter()
        .filter(|o| !o.is_stdio() && holds_data(o.path))
    {
        let Some(id) = identity(out.path) else {
            continue;
        };
        if let Some((_, input)) = known.iter().find(|(k, _)| *k == id) {
            return Err(Error::Usage(format!(
                "{} {} is the same file as {} {}: writing it would destroy an input; choose another output",
                out.what,
                out.path.display(),
                input.what,
                input.path.display()
            )));
        }
    }
    Ok(())
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;

    #[test]
    fn the_same_file_under_other_names_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let m = dir.path().join("m.csv");
        std::fs::write(&m, "t,i,y1\n").unwrap();
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        std::os::unix::fs::symlink(&m, dir.path().join("link.csv")).unwrap();
        let input = [Role::new("--meas", &m)];
        for alias in [
            m.clone(),
            dir.path().join("sub/../m.csv"),
            dir.path().join("link.csv"),
        ] {
            let err = check_files(&input, &[Role::new("--out", &alias)]).unwrap_err();
            let text = err.to_string();
            assert!(text.contains("--meas") && text.contains("--out"), "{text}");
            assert_eq!(err.exit_code(), 2);
        }
        let other = dir.path().join("e.csv");
        check_files(&input, &[Role::new("--out", &other)]).unwrap();
        check_files(&input, &[Role::new("--out", Path::new("-"))]).unwrap();
        check_files(&input, &[Role::new("--out", Path::new("/dev/null"))]).unwrap();
    }

    #[test]
    fn two_inputs_from_standard_input_are_refused() {
        let dash = Path::new("-");
        let err = check_files(
            &[Role::new("--meas", dash), Role::new("--truth", dash)],
            &[],
        )
        .unwrap_err();
        assert!(
            err.to_string()
                .contains("--meas and --truth cannot both read standard input")
        );
        check_files(&[Role::new("--meas", dash)], &[]).unwrap();
    }
}

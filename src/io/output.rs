//! Output destinations: standard output, or a file written atomically (a temporary file in the
//! target folder, renamed over the target only when everything was written), so that an error
//! or an interrupted run never leaves a half-written file and keeps the previous one intact.
//! The new file is on the disk before it replaces the old one (synced before the rename; a
//! file is synced as it grows, so that little is left to wait for at the end).
//! A destination that exists and is not a regular file (`/dev/null`, a named pipe, a terminal)
//! is written in place: renaming over it would replace the device or pipe with a file. A
//! symbolic link is written through: the file it points to is replaced, the link stays.
//!
//! A new file gets the permissions the umask allows (`0666 & !umask`, as `>` in a shell); a
//! replaced file keeps its own, so results a user made private stay private.
//!
//! The temporary files still open are listed in a registry, so that a run stopped by a signal
//! can remove them ([`remove_pending_files`]; the binary calls it on SIGINT, SIGTERM and
//! SIGHUP). Only SIGKILL leaves one behind: `.sisfilt-XXXXXX.tmp` beside the target.

use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::mpsc::{SyncSender, sync_channel};
use std::sync::{Mutex, MutexGuard};
use std::thread::JoinHandle;

use crate::error::{Error, Result};
use crate::io::folder_of;

const BUFFER: usize = 1 << 20;

/// The temporary files of every [`Output::File`] not yet committed or dropped.
static PENDING: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

fn pending() -> MutexGuard<'static, Vec<PathBuf>> {
    // A panic while holding the lock cannot leave the list inconsistent (push and retain).
    PENDING.lock().unwrap_or_else(|e| e.into_inner())
}

/// Removes every temporary output file still pending and returns with the registry locked,
/// so that no output can be committed afterwards: for a signal handler that then ends the
/// process. The previous outputs stay as they were.
pub fn remove_pending_files() -> MutexGuard<'static, Vec<PathBuf>> {
    let mut list = pending();
    for path in list.drain(..) {
        let _ = std::fs::remove_file(path);
    }
    list
}

/// Keeps a temporary file in the registry for as long as it lives.
pub struct Registration(PathBuf);

impl Registration {
    fn new(path: &Path) -> Self {
        pending().push(path.to_path_buf());
        Registration(path.to_path_buf())
    }
}

impl Drop for Registration {
    fn drop(&mut self) {
        pending().retain(|p| p != &self.0);
    }
}

/// Where a command writes one output.
pub enum Output {
    Stdout(HeldStdout),
    File {
        file: BufWriter<TempOutput>,
        /// The path as given, for messages.
        dest: PathBuf,
        /// The file replaced: `dest`, or where the symbolic link `dest` points.
        target: PathBuf,
        registration: Registration,
    },
    /// An existing destination that is not a regular file, opened for writing as it is.
    Special {
        file: BufWriter<std::fs::File>,
        dest: PathBuf,
    },
}

impl Output {
    /// `-` is standard output; anything else a file created atomically in an existing folder.
    pub fn create(dest: &Path) -> Result<Self> {
        if dest.as_os_str() == "-" {
            return Ok(Output::Stdout(HeldStdout {
                out: Some(BufWriter::with_capacity(BUFFER, std::io::stdout())),
                live: stdout_is_live(),
            }));
        }
        let target = link_target(dest).map_err(|e| Error::io(dest, e))?;
        let existing = std::fs::metadata(&target).ok();
        if existing
            .as_ref()
            .is_some_and(|m| !m.is_file() && !m.is_dir())
        {
            let file = std::fs::OpenOptions::new()
                .write(true)
                .open(&target)
                .map_err(|e| Error::io(dest, e))?;
            return Ok(Output::Special {
                file: BufWriter::with_capacity(BUFFER, file),
                dest: dest.to_path_buf(),
            });
        }
        if existing.as_ref().is_some_and(std::fs::Metadata::is_dir) {
            return Err(Error::io(
                dest,
                std::io::Error::new(
                    std::io::ErrorKind::IsADirectory,
                    "is a folder, expected a file path",
                ),
            ));
        }
        let dir = folder_of(&target);
        if !dir.is_dir() {
            return Err(Error::Usage(format!(
                "{}: the folder {} does not exist",
                dest.display(),
                dir.display()
            )));
        }
        let mut builder = tempfile::Builder::new();
        builder.prefix(".sisfilt-").suffix(".tmp");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            // Reduced by the umask when the file is created.
            builder.permissions(std::fs::Permissions::from_mode(0o666));
        }
        let tmp = builder.tempfile_in(dir).map_err(|e| {
            // tempfile's message names its random file; say which folder refused instead.
            let text = e.to_string();
            let cause = text.split(" at path ").next().unwrap_or_default();
            Error::io(
                dest,
                std::io::Error::new(
                    e.kind(),
                    format!(
                        "cannot create a file in the folder {}: {cause}",
                        dir.display()
                    ),
                ),
            )
        })?;
        let registration = Registration::new(tmp.path());
        if let Some(meta) = existing {
            // Set after creation, so that the umask cannot narrow what the file had.
            tmp.as_file()
                .set_permissions(meta.permissions())
                .map_err(|e| Error::io(dest, e))?;
        }
        Ok(Output::File {
            registration,
            // A small buffer, so that the file's bytes reach it (and its writeback) as they
            // come, not all at the end.
            file: BufWriter::with_capacity(FIRST_WRITEBACK as usize, TempOutput::new(tmp)),
            dest: dest.to_path_buf(),
            target,
        })
    }

    /// Whether a reader may be waiting on the other side (a pipe, a named pipe, a terminal,
    /// a socket: anything but a regular file), so that each step is worth passing on as soon
    /// as it is written ([`Write::flush`] then passes it on).
    pub fn is_live(&self) -> bool {
        match self {
            Output::Stdout(held) => held.live,
            Output::File { .. } => false,
            Output::Special { .. } => true,
        }
    }

    /// The path written to, or `<stdout>`, for messages.
    pub fn name(&self) -> String {
        match self {
            Output::Stdout(_) => "<stdout>".into(),
            Output::File { dest, .. } | Output::Special { dest, .. } => dest.display().to_string(),
        }
    }

    /// Flushes and, for a file, renames the temporary file over the destination.
    pub fn commit(self) -> Result<()> {
        match self {
            Output::Stdout(mut w) => w.finish().map_err(|e| Error::io("<stdout>", e)),
            Output::File {
                file,
                dest,
                target,
                registration,
            } => {
                let tmp = file
                    .into_inner()
                    .map_err(|e| Error::io(&dest, e.into_error()))?
                    .finish();
                tmp.as_file().sync_all().ok();
                // Under the registry's lock: a signal handler either removed the file before
                // (and the rename fails) or sees it already gone from the list.
                let mut list = pending();
                if !list.contains(&registration.0) {
                    return Err(Error::io(
                        &dest,
                        std::io::Error::new(std::io::ErrorKind::Interrupted, "interrupted"),
                    ));
                }
                let persisted = tmp.persist(&target);
                list.retain(|p| p != &registration.0);
                drop(list);
                persisted.map_err(|e| Error::io(&dest, e.error))?;
                Ok(())
            }
            Output::Special { mut file, dest } => file.flush().map_err(|e| Error::io(&dest, e)),
        }
    }
}

impl Write for Output {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match self {
            Output::Stdout(w) => w.write(buf),
            Output::File { file, .. } => file.write(buf),
            Output::Special { file, .. } => file.write(buf),
        }
    }

    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        match self {
            Output::Stdout(w) => w.write_all(buf),
            Output::File { file, .. } => file.write_all(buf),
            Output::Special { file, .. } => file.write_all(buf),
        }
    }

    fn flush(&mut self) -> std::io::Result<()> {
        match self {
            Output::Stdout(w) => w.flush(),
            Output::File { file, .. } => file.flush(),
            Output::Special { file, .. } => file.flush(),
        }
    }
}

/// The bytes a temporary output file takes before its pages are first sent to the disk, and
/// the write buffer before it: small outputs (a few hundred kilobytes) are mostly on the disk
/// when the run ends too.
const FIRST_WRITEBACK: u64 = 64 << 10;
/// The most bytes between two syncs of a growing file: the interval doubles from
/// [`FIRST_WRITEBACK`] up to this.
const WRITEBACK: u64 = 16 << 20;

/// A temporary output file whose pages go to the disk while it is written: after its first
/// 64 KiB, then after twice as many bytes since, and so on up to every 16 MiB
/// (`FIRST_WRITEBACK`, `WRITEBACK`), a thread of its own syncs what is there so far, so that
/// the sync before the rename (which makes the new file durable before it replaces the old
/// one) waits only for the last part instead of the whole file. The thread mostly waits on the
/// disk, and is started only once a file has its first 64 KiB.
pub struct TempOutput {
    tmp: tempfile::NamedTempFile,
    unsynced: u64,
    /// The unsynced bytes that call for the next sync.
    next_writeback: u64,
    writeback: Writeback,
}

/// The writeback thread of a [`TempOutput`].
enum Writeback {
    /// Not needed yet: the file is still under [`FIRST_WRITEBACK`] bytes.
    NotStarted,
    /// Woken by a message to sync; it ends when the sender is dropped.
    Running(SyncSender<()>, JoinHandle<()>),
    /// It could not be started: the final sync does all the work, as it would without it.
    Unavailable,
}

impl TempOutput {
    fn new(tmp: tempfile::NamedTempFile) -> Self {
        Self {
            tmp,
            unsynced: 0,
            next_writeback: FIRST_WRITEBACK,
            writeback: Writeback::NotStarted,
        }
    }

    /// Asks the writeback thread for a sync, starting it the first time; a request while one
    /// is pending is dropped, since that sync will cover these pages too.
    fn request_writeback(&mut self) {
        if let Writeback::NotStarted = self.writeback {
            let started = self.tmp.as_file().try_clone().and_then(|file| {
                let (request, requests) = sync_channel::<()>(1);
                let thread = std::thread::Builder::new()
                    .name("sisfilt-writeback".into())
                    .spawn(move || {
                        while requests.recv().is_ok() {
                            let _ = file.sync_data();
                        }
                    })?;
                Ok(Writeback::Running(request, thread))
            });
            self.writeback = started.unwrap_or(Writeback::Unavailable);
        }
        if let Writeback::Running(request, _) = &self.writeback {
            // Full: a sync is pending and will cover these pages; disconnected: the thread
            // is gone and the final sync does its work.
            let _ = request.try_send(());
        }
    }

    /// Stops the writeback thread (after the sync it may be doing) and returns the file.
    fn finish(mut self) -> tempfile::NamedTempFile {
        if let Writeback::Running(request, thread) =
            std::mem::replace(&mut self.writeback, Writeback::Unavailable)
        {
            drop(request);
            let _ = thread.join();
        }
        self.tmp
    }
}

impl Write for TempOutput {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let written = self.tmp.write(buf)?;
        self.unsynced += written as u64;
        if self.unsynced >= self.next_writeback {
            self.unsynced = 0;
            self.next_writeback = (2 * self.next_writeback).min(WRITEBACK);
            self.request_writeback();
        }
        Ok(written)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.tmp.flush()
    }
}

/// Where `dest` leads once every symbolic link on the way is followed (a link's relative
/// target is read from the link's folder); `dest` itself when it is no link. The result need
/// not exist: a dangling link names the file to create.
fn link_target(dest: &Path) -> std::io::Result<PathBuf> {
    // As many links as Linux follows before it reports a loop (ELOOP).
    const MAX_LINKS: usize = 40;
    let mut path = dest.to_path_buf();
    for _ in 0..MAX_LINKS {
        match std::fs::symlink_metadata(&path) {
            Ok(meta) if meta.file_type().is_symlink() => {
                let next = std::fs::read_link(&path)?;
                path = match path.parent() {
                    Some(dir) if next.is_relative() => dir.join(next),
                    _ => next,
                };
            }
            _ => return Ok(path),
        }
    }
    Err(std::io::Error::new(
        std::io::ErrorKind::InvalidInput,
        "too many levels of symbolic links",
    ))
}

/// Buffered standard output. Redirected to a regular file, it is only flushed by
/// `HeldStdout::finish`: dropped on an error path, it discards what it still holds, so a
/// failed run writes at most what had already overflowed the 1 MiB buffer (nothing, for most
/// outputs). Live (a pipe or a terminal), [`Write::flush`] passes on what it holds, so that a
/// reader gets each step as it is written.
pub struct HeldStdout {
    out: Option<BufWriter<std::io::Stdout>>,
    live: bool,
}

/// Whether standard output is anything but a regular file.
fn stdout_is_live() -> bool {
    #[cfg(unix)]
    {
        use std::os::fd::AsFd;
        let meta = std::io::stdout()
            .as_fd()
            .try_clone_to_owned()
            .map(std::fs::File::from)
            .and_then(|f| f.metadata());
        meta.map_or(true, |m| !m.is_file())
    }
    #[cfg(not(unix))]
    {
        use std::io::IsTerminal;
        std::io::stdout().is_terminal()
    }
}

impl HeldStdout {
    fn finish(&mut self) -> std::io::Result<()> {
        match self.out.take() {
            Some(mut w) => w.flush(),
            None => Ok(()),
        }
    }

    fn inner(&mut self) -> &mut BufWriter<std::io::Stdout> {
        self.out
            .as_mut()
            .expect("standard output used after finish")
    }
}

impl Drop for HeldStdout {
    fn drop(&mut self) {
        if let Some(w) = self.out.take() {
            let _ = w.into_parts();
        }
    }
}

impl Write for HeldStdout {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.inner().write(buf)
    }

    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        self.inner().write_all(buf)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        // Into a file, flushing is for `finish`: intermediate flushes would pass partial
        // output on.
        if self.live {
            self.inner().flush()
        } else {
            Ok(())
        }
    }
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;
    use std::io::Read;
    use std::os::unix::fs::FileTypeExt;

    /// A named pipe (like `/dev/null`, a file that is not a regular one) is written in place:
    /// renaming a temporary file over it would replace the pipe with a plain file.
    #[test]
    fn special_files_are_written_in_place() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe");
        let status = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .expect("mkfifo runs");
        assert!(status.success());
        let reader = {
            let fifo = fifo.clone();
            std::thread::spawn(move || {
                let mut text = String::new();
                std::fs::File::open(fifo)
                    .unwrap()
                    .read_to_string(&mut text)
                    .unwrap();
                text
            })
        };
        let mut out = Output::create(&fifo).unwrap();
        assert!(matches!(out, Output::Special { .. }));
        out.write_all(b"t,i\n1,1\n").unwrap();
        out.commit().unwrap();
        assert_eq!(reader.join().unwrap(), "t,i\n1,1\n");
        assert!(std::fs::metadata(&fifo).unwrap().file_type().is_fifo());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn regular_files_are_replaced_atomically() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.csv");
        std::fs::write(&path, "old").unwrap();
        let mut out = Output::create(&path).unwrap();
        assert!(matches!(out, Output::File { .. }));
        out.write_all(b"new").unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "old");
        out.commit().unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "new");
    }

    /// A file larger than [`WRITEBACK`] is synced by the writeback thread as it grows, and
    /// comes out whole; given up half way, it leaves the previous file and nothing else.
    #[test]
    fn large_files_are_written_back_as_they_grow() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.csv");
        std::fs::write(&path, "old").unwrap();
        let bytes: Vec<u8> = (0..3 * WRITEBACK + 12_345)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
            .collect();
        let started = |out: &Output| match out {
            Output::File { file, .. } => {
                matches!(file.get_ref().writeback, Writeback::Running(..))
            }
            _ => panic!("a regular file"),
        };
        let mut out = Output::create(&path).unwrap();
        for chunk in bytes.chunks(999_983) {
            out.write_all(chunk).unwrap();
        }
        assert!(started(&out));
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "old");
        out.commit().unwrap();
        assert!(std::fs::read(&path).unwrap() == bytes);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);

        let mut out = Output::create(&path).unwrap();
        out.write_all(&bytes[..2 * WRITEBACK as usize]).unwrap();
        assert!(started(&out));
        drop(out);
        assert!(std::fs::read(&path).unwrap() == bytes);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    /// A file of a few hundred kilobytes starts its writeback at [`FIRST_WRITEBACK`] bytes,
    /// not before, and asks for the next sync after twice as many bytes each time, up to
    /// [`WRITEBACK`].
    #[test]
    fn small_files_are_written_back_from_the_first_writeback() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.csv");
        let bytes: Vec<u8> = (0..300_000u32).map(|i| (i % 251) as u8).collect();
        let temp = |out: &Output| match out {
            Output::File { file, .. } => (
                matches!(file.get_ref().writeback, Writeback::Running(..)),
                file.get_ref().next_writeback,
            ),
            _ => panic!("a regular file"),
        };
        let mut out = Output::create(&path).unwrap();
        // The buffer passes on nothing below its size: no writeback yet.
        out.write_all(&bytes[..FIRST_WRITEBACK as usize - 1])
            .unwrap();
        assert_eq!(temp(&out), (false, FIRST_WRITEBACK));
        out.write_all(&bytes[FIRST_WRITEBACK as usize - 1..])
            .unwrap();
        assert!(temp(&out).0);
        assert!(temp(&out).1 > FIRST_WRITEBACK);
        out.commit().unwrap();
        assert!(std::fs::read(&path).unwrap() == bytes);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);

        // The interval doubles up to WRITEBACK.
        let tmp = tempfile::NamedTempFile::new_in(dir.path()).unwrap();
        let mut grown = TempOutput::new(tmp);
        let mut expected = FIRST_WRITEBACK;
        let mut at_most = 0;
        while at_most < 2 {
            grown.write_all(&vec![0; expected as usize]).unwrap();
            expected = (2 * expected).min(WRITEBACK);
            assert_eq!(grown.next_writeback, expected);
            at_most += usize::from(expected == WRITEBACK);
        }
        drop(grown.finish());
    }

    /// A symbolic link is written through: its target gets the new bytes and keeps its mode,
    /// the link stays a link.
    #[test]
    fn links_are_written_through_and_modes_kept() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("data")).unwrap();
        let target = dir.path().join("data/out.csv");
        std::fs::write(&target, "old").unwrap();
        std::fs::set_permissions(&target, std::fs::Permissions::from_mode(0o640)).unwrap();
        let link = dir.path().join("link.csv");
        std::os::unix::fs::symlink("data/out.csv", &link).unwrap();
        let mut out = Output::create(&link).unwrap();
        out.write_all(b"new").unwrap();
        out.commit().unwrap();
        assert!(
            std::fs::symlink_metadata(&link)
                .unwrap()
                .file_type()
                .is_symlink()
        );
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "new");
        let mode = std::fs::metadata(&target).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o640);
        assert_eq!(
            std::fs::read_dir(dir.path().join("data")).unwrap().count(),
            1
        );

        // A dangling link names the file to create.
        std::fs::remove_file(&target).unwrap();
        let mut out = Output::create(&link).unwrap();
        out.write_all(b"created").unwrap();
        out.commit().unwrap();
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "created");
        assert!(
            std::fs::symlink_metadata(&link)
                .unwrap()
                .file_type()
                .is_symlink()
        );
    }
}

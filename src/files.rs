//! Reading the files a user or a run folder names: only regular files (opening a FIFO blocks
//! until someone writes to it, a device never ends, a folder is no file), and never more bytes
//! than the caller expects, so a symlink to /dev/zero or a sparse file of terabytes is refused
//! before any of it is read. Errors are I/O errors (`InvalidInput` for what is not a file,
//! `FileTooLarge` past the bound), so each reader's own error type keeps them as its source.

use std::io::{Error, ErrorKind, Read};
use std::path::{Path, PathBuf};

fn not_a_file() -> Error {
    Error::new(
        ErrorKind::InvalidInput,
        "not a regular file (a FIFO, a device or a folder); only files are read or replaced",
    )
}

/// The length of the regular file at `path` (through symlinks), checked without opening it.
pub fn regular_len(path: &Path) -> std::io::Result<u64> {
    let meta = std::fs::metadata(path)?;
    if !meta.is_file() {
        return Err(not_a_file());
    }
    Ok(meta.len())
}

/// Opens `path` for reading only if it is a regular file. The open itself cannot block: it is
/// made non-blocking (a FIFO without a writer would otherwise wait in `open` for ever) and the
/// opened handle, not the name, is checked, so a file swapped for a FIFO meanwhile is refused
/// too.
pub fn open_regular(path: &Path) -> std::io::Result<std::fs::File> {
    use std::os::unix::fs::OpenOptionsExt;
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)?;
    if !file.metadata()?.is_file() {
        return Err(not_a_file());
    }
    Ok(file)
}

/// Creates (or truncates) `path` for writing only if it is, or becomes, a regular file; non-
/// blocking like [`open_regular`], so a FIFO without a reader at `path` fails at once.
pub fn create_regular(path: &Path) -> std::io::Result<std::fs::File> {
    use std::os::unix::fs::OpenOptionsExt;
    let file = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)?;
    if !file.metadata()?.is_file() {
        return Err(not_a_file());
    }
    Ok(file)
}

/// Whether a new file may be renamed onto `path`: nothing is there, or a regular file (through
/// symlinks). A FIFO, a device or a folder is never replaced.
pub fn check_replaceable(path: &Path) -> std::io::Result<()> {
    match std::fs::metadata(path) {
        Ok(meta) if !meta.is_file() => Err(not_a_file()),
        _ => Ok(()),
    }
}

/// The whole of a regular file of at most `max` bytes. The length is checked before a byte is
/// read and the read stops one byte past `max`, so a file that grows meanwhile is refused too.
pub fn read_capped(path: &Path, max: u64) -> std::io::Result<Vec<u8>> {
    let file = open_regular(path)?;
    let too_large = |len: u64| {
        Error::new(
            ErrorKind::FileTooLarge,
            format!("{len} bytes, more than the {max} it may have"),
        )
    };
    let len = file.metadata()?.len();
    if len > max {
        return Err(too_large(len));
    }
    let mut bytes = Vec::with_capacity(len as usize);
    file.take(max + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

/// [`read_capped`] as UTF-8 text.
pub fn read_text_capped(path: &Path, max: u64) -> std::io::Result<String> {
    String::from_utf8(read_capped(path, max)?).map_err(|e| Error::new(ErrorKind::InvalidData, e))
}

/// Makes a FIFO at `path`, for tests. By the system call, not by running `mkfifo`: a child
/// process forked beside a test holds copies of its open files (and their locks) until it execs,
/// which made a run-folder lock test fail now and then.
/// A fresh folder only this user may enter (mode 0700, under the temp dir), removed with
/// everything in it when dropped: `live --web` keeps the Unix sockets of the servers behind its
/// guards in one, so no other user's process can reach them.
pub struct PrivateDir {
    path: PathBuf,
}

impl PrivateDir {
    /// `<temp dir>/<prefix>-<pid>-<64 random bits>`, created new (an existing entry of that name
    /// is an error: nobody else's folder is ever used).
    pub fn create(prefix: &str) -> std::io::Result<Self> {
        use std::os::unix::fs::DirBuilderExt;
        let name = format!(
            "{prefix}-{}-{:016x}",
            std::process::id(),
            rand::random::<u64>()
        );
        let path = std::env::temp_dir().join(name);
        std::fs::DirBuilder::new().mode(0o700).create(&path)?;
        Ok(Self { path })
    }

    /// The entry `name` in it (`control.sock`, …).
    pub fn join(&self, name: &str) -> PathBuf {
        self.path.join(name)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for PrivateDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.path);
    }
}

#[cfg(test)]
pub(crate) fn mkfifo(path: &Path) {
    use std::os::unix::ffi::OsStrExt;
    let name = std::ffi::CString::new(path.as_os_str().as_bytes()).expect("no NUL in a temp path");
    // SAFETY: `name` is a valid NUL-terminated path that outlives the call.
    let rc = unsafe { libc::mkfifo(name.as_ptr(), 0o600) };
    assert_eq!(rc, 0, "mkfifo {}", path.display());
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_private_dir_is_new_mode_0700_and_gone_when_dropped() {
        use std::os::unix::fs::MetadataExt;
        let a = PrivateDir::create("gaitscope-test").unwrap();
        let b = PrivateDir::create("gaitscope-test").unwrap();
        assert_ne!(a.path(), b.path());
        assert_eq!(std::fs::metadata(a.path()).unwrap().mode() & 0o777, 0o700);
        std::fs::write(a.join("x.sock"), b"").unwrap();
        let path = a.path().to_path_buf();
        drop(a);
        assert!(!path.exists());
    }

    #[test]
    fn only_regular_files_of_bounded_size_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a.bin");
        std::fs::write(&file, [7u8; 100]).unwrap();
        assert_eq!(read_capped(&file, 100).unwrap(), vec![7u8; 100]);
        assert_eq!(regular_len(&file).unwrap(), 100);
        let err = read_capped(&file, 99).unwrap_err();
        assert_eq!(err.kind(), ErrorKind::FileTooLarge);
        assert_eq!(err.to_string(), "100 bytes, more than the 99 it may have");
        // A folder, a device and a missing file.
        for not_file in [dir.path(), Path::new("/dev/zero"), Path::new("/dev/null")] {
            assert_eq!(
                read_capped(not_file, 10).unwrap_err().kind(),
                ErrorKind::InvalidInput,
                "{}",
                not_file.display()
            );
            assert_eq!(
                regular_len(not_file).unwrap_err().kind(),
                ErrorKind::InvalidInput
            );
        }
        let missing = dir.path().join("none");
        assert_eq!(
            read_capped(&missing, 10).unwrap_err().kind(),
            ErrorKind::NotFound
        );
        // A symlink to a device is judged by what it points to.
        let link = dir.path().join("zero.bin");
        std::os::unix::fs::symlink("/dev/zero", &link).unwrap();
        let err = read_capped(&link, 10).unwrap_err();
        assert!(err.to_string().contains("not a regular file"), "{err}");
        // Text that is not UTF-8.
        std::fs::write(&file, [0xff, 0xfe]).unwrap();
        assert_eq!(
            read_text_capped(&file, 10).unwrap_err().kind(),
            ErrorKind::InvalidData
        );
    }

    /// A FIFO is refused at once: opening it for reading would block until a writer came, and
    /// none will.
    #[test]
    fn a_fifo_is_refused_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("replay.bin");
        mkfifo(&fifo);
        let started = std::time::Instant::now();
        for err in [
            read_capped(&fifo, 1 << 20).unwrap_err(),
            open_regular(&fifo).unwrap_err(),
            regular_len(&fifo).unwrap_err(),
        ] {
            assert_eq!(err.kind(), ErrorKind::InvalidInput);
        }
        assert!(started.elapsed() < std::time::Duration::from_secs(5));
    }
}

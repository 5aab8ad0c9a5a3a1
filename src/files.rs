//! Reading the files a user or a run folder names: only regular files (opening a FIFO blocks
//! until someone writes to it, a device never ends, a folder is no file), and never more bytes
//! than the caller expects, so a symlink to /dev/zero or a sparse file of terabytes is refused
//! before any of it is read.

use std::io::Read;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum FileError {
    #[error("cannot read {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path} is not a regular file (a FIFO, a device or a folder); only files are read")]
    NotAFile { path: PathBuf },
    #[error("{path} holds {len} bytes, more than the {max} it may have")]
    TooLarge { path: PathBuf, len: u64, max: u64 },
}

impl FileError {
    /// The file is not there (a missing optional file is often no error).
    pub fn is_not_found(&self) -> bool {
        matches!(self, FileError::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound)
    }
}

/// The length of the regular file at `path` (through symlinks), checked without opening it.
pub fn regular_len(path: &Path) -> Result<u64, FileError> {
    let meta = std::fs::metadata(path).map_err(|source| FileError::Io {
        path: path.to_owned(),
        source,
    })?;
    if !meta.is_file() {
        return Err(FileError::NotAFile {
            path: path.to_owned(),
        });
    }
    Ok(meta.len())
}

/// The whole of a regular file of at most `max` bytes. The length is checked before the file
/// is opened and the read stops one byte past `max`, so a file that grows meanwhile is refused
/// too.
pub fn read_capped(path: &Path, max: u64) -> Result<Vec<u8>, FileError> {
    let len = regular_len(path)?;
    let too_large = |len| FileError::TooLarge {
        path: path.to_owned(),
        len,
        max,
    };
    if len > max {
        return Err(too_large(len));
    }
    let io = |source| FileError::Io {
        path: path.to_owned(),
        source,
    };
    let mut bytes = Vec::with_capacity(len as usize);
    std::fs::File::open(path)
        .and_then(|f| f.take(max + 1).read_to_end(&mut bytes))
        .map_err(io)?;
    if bytes.len() as u64 > max {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_regular_files_of_bounded_size_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a.bin");
        std::fs::write(&file, [7u8; 100]).unwrap();
        assert_eq!(read_capped(&file, 100).unwrap(), vec![7u8; 100]);
        assert_eq!(regular_len(&file).unwrap(), 100);
        let err = read_capped(&file, 99).unwrap_err();
        assert!(
            matches!(
                err,
                FileError::TooLarge {
                    len: 100,
                    max: 99,
                    ..
                }
            ),
            "{err}"
        );
        // A folder, a device and a missing file.
        assert!(matches!(
            read_capped(dir.path(), 10),
            Err(FileError::NotAFile { .. })
        ));
        assert!(matches!(
            read_capped(Path::new("/dev/zero"), 10),
            Err(FileError::NotAFile { .. })
        ));
        let missing = read_capped(&dir.path().join("none"), 10).unwrap_err();
        assert!(missing.is_not_found(), "{missing}");
        // A symlink to a device is judged by what it points to.
        let link = dir.path().join("zero.bin");
        std::os::unix::fs::symlink("/dev/zero", &link).unwrap();
        let err = read_capped(&link, 10).unwrap_err();
        assert!(err.to_string().contains("not a regular file"), "{err}");
    }

    /// A FIFO is refused without being opened: opening it for reading would block until a
    /// writer came, and none will.
    #[test]
    fn a_fifo_is_refused_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("replay.bin");
        let status = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap();
        assert!(status.success());
        let started = std::time::Instant::now();
        assert!(matches!(
            read_capped(&fifo, 1 << 20),
            Err(FileError::NotAFile { .. })
        ));
        assert!(started.elapsed() < std::time::Duration::from_secs(5));
    }
}

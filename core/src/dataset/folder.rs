//! A dataset folder whose contents are not trusted (an upload): every file it names is
//! confined to it.
//!
//! A name must be a relative path without `..`, and resolving it (symbolic links included)
//! must land inside the folder. Errors name files as the dataset does (relative), never by
//! their place on this machine, and a name that is refused is refused whether or not the file
//! it points at exists, so the answer reveals nothing about files outside.

use std::path::{Component, Path, PathBuf};

use crate::{Error, Result};

/// A dataset folder, resolved once.
#[derive(Clone, Debug)]
pub struct SequenceFolder {
    /// The folder as given; paths handed out keep this prefix.
    dir: PathBuf,
    /// Its canonical form, inside which every resolved file must lie.
    real: PathBuf,
}

impl SequenceFolder {
    /// The folder `dir` (which must exist).
    pub fn new(dir: &Path) -> Result<Self> {
        let real = dir.canonicalize().map_err(|e| Error::io(dir, e))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            real,
        })
    }

    /// The folder's own name (camera presets are recognised from it).
    pub fn folder_name(&self) -> String {
        self.dir
            .file_name()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default()
    }

    /// `path` as the dataset names it (relative to the folder), for messages.
    pub fn name<'a>(&self, path: &'a Path) -> &'a Path {
        path.strip_prefix(&self.dir).unwrap_or(path)
    }

    /// The path of `rel` inside the folder when it names an existing file there, `None` when
    /// nothing is there. `what` says in errors where the name came from.
    fn confined(&self, rel: &str, what: &dyn Fn() -> String) -> Result<Option<PathBuf>> {
        let path = Path::new(rel);
        let relative = !rel.is_empty()
            && path
                .components()
                .all(|c| matches!(c, Component::Normal(_) | Component::CurDir));
        if !relative {
            return Err(Error::Dataset(format!(
                "{}: `{rel}` must be a relative path inside the dataset folder (no `..`, no \
                 absolute path)",
                what()
            )));
        }
        let joined = self.dir.join(path);
        let real = match joined.canonicalize() {
            Ok(real) => real,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(Error::io(rel, e)),
        };
        if !real.starts_with(&self.real) {
            return Err(Error::Dataset(format!(
                "{}: `{rel}` leads outside the dataset folder (symbolic link)",
                what()
            )));
        }
        Ok(real.is_file().then_some(joined))
    }

    /// The text of one of the folder's own files (`rgb.txt`, `calibration.txt`, ...), or
    /// `None` when it has none; a file of more than `max_bytes` is refused before reading.
    pub fn read_own(&self, name: &str, max_bytes: u64) -> Result<Option<String>> {
        let Some(path) = self.confined(name, &|| name.to_string())? else {
            return Ok(None);
        };
        let bytes =
            read_at_most(&path, max_bytes).map_err(|e| e.named(Path::new(name), "a text file"))?;
        String::from_utf8(bytes)
            .map(Some)
            .map_err(|_| Error::Dataset(format!("{name} is not UTF-8 text")))
    }

    /// The file a list names in its `line`-th entry; it must exist.
    pub fn listed(&self, rel: &str, list: &str, entry: usize) -> Result<PathBuf> {
        let what = || format!("{list}, entry {entry}");
        self.confined(rel, &what)?
            .ok_or_else(|| Error::Dataset(format!("{}: listed file {rel} does not exist", what())))
    }
}

/// Why [`read_at_most`] failed.
#[derive(Debug)]
pub(crate) enum BoundedReadError {
    /// The file holds more than the limit (its size, or what was read).
    TooLarge {
        size: u64,
        limit: u64,
    },
    Io(std::io::Error),
}

impl BoundedReadError {
    /// The dataset error, naming the file as the dataset does and what kind of file (`an
    /// image`, `a text file`) the limit is for.
    pub(crate) fn named(self, name: &Path, kind: &str) -> Error {
        match self {
            BoundedReadError::TooLarge { size, limit } => Error::Dataset(format!(
                "{} holds {size} bytes, more than the {limit} allowed for {kind}",
                name.display()
            )),
            BoundedReadError::Io(e) => Error::io(name, e),
        }
    }
}

/// The bytes of `path`, refused from its size before reading when it holds more than `limit`
/// (and while reading, should it grow meanwhile).
pub(crate) fn read_at_most(
    path: &Path,
    limit: u64,
) -> std::result::Result<Vec<u8>, BoundedReadError> {
    use std::io::Read as _;
    let file = std::fs::File::open(path).map_err(BoundedReadError::Io)?;
    let size = file.metadata().map_err(BoundedReadError::Io)?.len();
    if size > limit {
        return Err(BoundedReadError::TooLarge { size, limit });
    }
    let mut bytes = Vec::with_capacity(usize::try_from(size).unwrap_or(0));
    file.take(limit.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(BoundedReadError::Io)?;
    if bytes.len() as u64 > limit {
        return Err(BoundedReadError::TooLarge {
            size: bytes.len() as u64,
            limit,
        });
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("relfusion-folder-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(d.join("seq/rgb")).expect("temp");
        d
    }

    #[test]
    fn names_inside_resolve_and_every_escape_is_refused_alike() {
        let root = temp("escape");
        let seq = root.join("seq");
        std::fs::write(seq.join("rgb/a.png"), b"x").expect("write");
        std::fs::write(root.join("secret.txt"), b"s").expect("write");
        std::os::unix::fs::symlink(root.join("secret.txt"), seq.join("rgb/link.png"))
            .expect("symlink");
        std::os::unix::fs::symlink(&root, seq.join("up")).expect("symlink");
        let folder = SequenceFolder::new(&seq).expect("folder");
        assert_eq!(
            folder.listed("rgb/a.png", "rgb.txt", 1).expect("inside"),
            seq.join("rgb/a.png")
        );
        assert!(folder.listed("./rgb/a.png", "rgb.txt", 1).is_ok());
        for bad in [
            "/etc/passwd",
            "/nonexistent/file",
            "../secret.txt",
            "../missing.txt",
            "rgb/../../secret.txt",
            "rgb/link.png",
            "up/secret.txt",
            "",
        ] {
            let e = folder.listed(bad, "rgb.txt", 3).expect_err(bad).to_string();
            assert!(e.contains("rgb.txt, entry 3"), "{bad}: {e}");
            assert!(
                !e.contains(root.to_string_lossy().as_ref()),
                "{bad}: the error shows where the folder is: {e}"
            );
        }
        let missing = folder
            .listed("rgb/b.png", "rgb.txt", 2)
            .expect_err("missing");
        assert!(missing.to_string().contains("does not exist"), "{missing}");
        assert_eq!(
            folder.read_own("calibration.txt", 1 << 20).expect("absent"),
            None
        );
        let _ = std::fs::remove_dir_all(root);
    }
}

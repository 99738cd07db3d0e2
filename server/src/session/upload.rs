//! Safe extraction of uploaded dataset archives (`.tar` via the `tar` crate, `.zip` via the
//! `zip` crate) and the TUM layout check.
//!
//! An archive is untrusted input: every entry path must be relative and stay inside the
//! destination (no `..`, no absolute path), links are refused (a symlink entry followed by a
//! file "inside" it is the classic escape), and the number of entries and the extracted bytes
//! are bounded — in total and relative to the archive's own size (zip bombs) — while
//! extracting; a zip's entry count is read from its end record before its central directory
//! is parsed, so a million-entry zip is refused at once. Entry names are bounded (components
//! of at most 255 bytes, 1024 in all) and every error names entries as the archive does,
//! never where they are on this machine. Once everything is written, one `syncfs` makes every
//! file and folder durable (an fsync per entry cost a 25 000-entry archive over a minute), so
//! that once the caller renames the folder into place and acknowledges the upload, it
//! survives a crash. The dataset inside is then read through
//! [`relfusion_slam::dataset::SequenceFolder`]: every file its lists name must stay inside it.

use std::collections::BTreeSet;
use std::fs::File;
use std::io::{BufReader, Read, Write};
use std::path::{Component, Path, PathBuf};

use relfusion_slam::dataset::{SequenceLimits, TumSequence};
use relfusion_slam::geometry::PinholeCamera;
use serde::{Deserialize, Serialize};

use crate::ApiError;
use crate::config::Limits;
use crate::storage::{create_dirs_durably, sync_dir};

/// The archive format of an upload.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ArchiveKind {
    Tar,
    Zip,
}

impl std::str::FromStr for ArchiveKind {
    type Err = ApiError;
    fn from_str(s: &str) -> Result<Self, ApiError> {
        match s {
            "tar" => Ok(Self::Tar),
            "zip" => Ok(Self::Zip),
            other => Err(ApiError::bad_request(format!(
                "format must be tar or zip, got {other:?}"
            ))),
        }
    }
}

/// Bounds of one extraction.
#[derive(Clone, Copy, Debug)]
pub struct ExtractLimits {
    pub max_bytes: u64,
    pub max_entries: usize,
    /// What reading the extracted dataset may cost.
    pub sequence: SequenceLimits,
}

impl ExtractLimits {
    /// The bounds for `archive` under `limits`: at most `max_extracted_bytes`, and at most
    /// `max_expansion_ratio` times the archive's size (at least that many MiB).
    pub fn for_archive(limits: &Limits, archive: &Path) -> Result<Self, ApiError> {
        let size = std::fs::metadata(archive).map_err(internal(archive))?.len();
        let ratio = limits.max_expansion_ratio;
        let by_ratio = (size.max(1 << 20) as f64 * ratio).min(u64::MAX as f64) as u64;
        Ok(Self {
            max_bytes: limits.max_extracted_bytes.min(by_ratio),
            max_entries: limits.max_upload_entries,
            sequence: limits.sequence_limits(),
        })
    }
}

/// A staged upload: where its dataset is, its camera, frames and bytes on disk.
#[derive(Debug)]
pub struct Staged {
    /// The dataset folder relative to the upload folder.
    pub dataset_rel: PathBuf,
    pub camera: PinholeCamera,
    pub frames: usize,
    /// Bytes extracted.
    pub bytes: u64,
}

/// Longest entry name component in bytes (what Linux file systems take).
pub const MAX_NAME_BYTES: usize = 255;
/// Longest entry path in bytes.
pub const MAX_PATH_BYTES: usize = 1024;

/// An entry name for messages: as the archive gives it, cut after 120 characters.
fn shown(raw: &Path) -> String {
    let text = raw.to_string_lossy();
    match text.char_indices().nth(120) {
        Some((cut, _)) => format!("{}…", &text[..cut]),
        None => text.into_owned(),
    }
}

/// The validated relative path of an archive entry: only normal components (`.` is skipped);
/// `..`, a root or a drive prefix, or a name longer than [`MAX_NAME_BYTES`] /
/// [`MAX_PATH_BYTES`] is a 400.
pub fn safe_relative_path(raw: &Path) -> Result<PathBuf, ApiError> {
    if raw.as_os_str().len() > MAX_PATH_BYTES {
        return Err(ApiError::bad_request(format!(
            "archive entry {} has a name of {} bytes, more than {MAX_PATH_BYTES}",
            shown(raw),
            raw.as_os_str().len()
        )));
    }
    let mut out = PathBuf::new();
    for component in raw.components() {
        match component {
            Component::Normal(part) if part.len() > MAX_NAME_BYTES => {
                return Err(ApiError::bad_request(format!(
                    "archive entry {} has a path component of {} bytes, more than \
                     {MAX_NAME_BYTES}",
                    shown(raw),
                    part.len()
                )));
            }
            Component::Normal(part) => out.push(part),
            Component::CurDir => {}
            Component::ParentDir => {
                return Err(ApiError::bad_request(format!(
                    "archive entry {} leaves the archive (`..`)",
                    raw.display()
                )));
            }
            Component::RootDir | Component::Prefix(_) => {
                return Err(ApiError::bad_request(format!(
                    "archive entry {} is an absolute path",
                    raw.display()
                )));
            }
        }
    }
    Ok(out)
}

/// Writes the files of one archive under `dest` and makes them durable.
struct Extractor<'a> {
    dest: &'a Path,
    limits: ExtractLimits,
    bytes: u64,
    entries: usize,
    dirs: BTreeSet<PathBuf>,
}

fn internal(path: &Path) -> impl FnOnce(std::io::Error) -> ApiError + '_ {
    move |e| ApiError::internal(format!("storing {}: {e}", path.display()))
}

/// An error writing entry `rel`: a 400 where the name is what the file system refuses, else a
/// 500; either names the entry as the archive does (the full path goes to the log only).
fn entry_error(rel: &Path, path: &Path) -> impl FnOnce(std::io::Error) -> ApiError {
    let (rel, path) = (rel.to_path_buf(), path.to_path_buf());
    move |e| {
        if e.kind() == std::io::ErrorKind::InvalidFilename
            || e.raw_os_error() == Some(36 /* ENAMETOOLONG */)
        {
            return ApiError::bad_request(format!(
                "archive entry {}: the name is not valid here ({e})",
                shown(&rel)
            ));
        }
        tracing::error!("storing upload entry {}: {e}", path.display());
        ApiError::internal(format!("storing archive entry {}: {e}", shown(&rel)))
    }
}

impl<'a> Extractor<'a> {
    fn new(dest: &'a Path, limits: ExtractLimits) -> Self {
        let mut dirs = BTreeSet::new();
        dirs.insert(dest.to_path_buf());
        Self {
            dest,
            limits,
            bytes: 0,
            entries: 0,
            dirs,
        }
    }

    fn count_entry(&mut self) -> Result<(), ApiError> {
        self.entries += 1;
        if self.entries > self.limits.max_entries {
            return Err(ApiError::payload_too_large(format!(
                "the archive has more than {} entries (limits.max_upload_entries)",
                self.limits.max_entries
            )));
        }
        Ok(())
    }

    fn dir(&mut self, rel: &Path) -> Result<(), ApiError> {
        let mut path = self.dest.to_path_buf();
        for part in rel.components() {
            path.push(part);
            if self.dirs.insert(path.clone()) {
                match std::fs::symlink_metadata(&path) {
                    Ok(m) if m.is_dir() => {}
                    Ok(_) => {
                        return Err(ApiError::bad_request(format!(
                            "archive entry {} is both a file and a folder",
                            rel.display()
                        )));
                    }
                    Err(_) => std::fs::create_dir(&path).map_err(entry_error(rel, &path))?,
                }
            }
        }
        Ok(())
    }

    fn file(&mut self, rel: &Path, reader: &mut dyn Read) -> Result<(), ApiError> {
        if rel.as_os_str().is_empty() {
            return Err(ApiError::bad_request("archive entry with an empty name"));
        }
        if let Some(parent) = rel.parent() {
            self.dir(parent)?;
        }
        let path = self.dest.join(rel);
        if self.dirs.contains(&path) {
            return Err(ApiError::bad_request(format!(
                "archive entry {} is both a folder and a file",
                rel.display()
            )));
        }
        let mut file = File::create(&path).map_err(entry_error(rel, &path))?;
        let budget = self.limits.max_bytes.saturating_sub(self.bytes);
        let mut limited = reader.take(budget + 1);
        let n = std::io::copy(&mut limited, &mut file).map_err(|e| {
            ApiError::bad_request(format!(
                "archive entry {}: {e} (truncated or corrupt archive?)",
                rel.display()
            ))
        })?;
        if n > budget {
            return Err(ApiError::payload_too_large(format!(
                "the archive extracts to more than {} bytes (limits.max_extracted_bytes, and \
                 limits.max_expansion_ratio times its own size)",
                self.limits.max_bytes
            )));
        }
        self.bytes += n;
        file.flush().map_err(entry_error(rel, &path))
    }

    /// Makes every new file and folder durable at once: one `syncfs` of the file system that
    /// holds them (its data and metadata), instead of an fsync per entry.
    fn sync(&self) -> Result<(), ApiError> {
        let dest = File::open(self.dest).map_err(internal(self.dest))?;
        rustix::fs::syncfs(&dest)
            .map_err(|e| ApiError::internal(format!("making the upload durable: {e}")))
    }
}

/// Extracts `archive` into the (new, empty) folder `dest`; returns the bytes written.
pub fn extract(
    archive: &Path,
    kind: ArchiveKind,
    dest: &Path,
    limits: ExtractLimits,
) -> Result<u64, ApiError> {
    create_dirs_durably(dest).map_err(|e| ApiError::internal(e.to_string()))?;
    let mut ex = Extractor::new(dest, limits);
    match kind {
        ArchiveKind::Tar => extract_tar(archive, &mut ex)?,
        ArchiveKind::Zip => extract_zip(archive, &mut ex)?,
    }
    ex.sync()?;
    Ok(ex.bytes)
}

fn extract_tar(archive: &Path, ex: &mut Extractor<'_>) -> Result<(), ApiError> {
    let file = File::open(archive).map_err(internal(archive))?;
    let mut ar = tar::Archive::new(BufReader::new(file));
    let bad = |e: std::io::Error| ApiError::bad_request(format!("invalid tar archive: {e}"));
    for entry in ar.entries().map_err(bad)? {
        let mut entry = entry.map_err(bad)?;
        ex.count_entry()?;
        let raw = entry.path().map_err(bad)?.into_owned();
        let rel = safe_relative_path(&raw)?;
        use tar::EntryType as T;
        match entry.header().entry_type() {
            T::Regular | T::Continuous => ex.file(&rel, &mut entry)?,
            T::Directory => ex.dir(&rel)?,
            T::Symlink | T::Link => {
                return Err(ApiError::bad_request(format!(
                    "archive entry {} is a link; links are not allowed",
                    raw.display()
                )));
            }
            // Metadata entries the tar crate has not folded into the next header.
            T::XGlobalHeader | T::XHeader | T::GNULongName | T::GNULongLink => {}
            other => {
                return Err(ApiError::bad_request(format!(
                    "archive entry {} has unsupported type {other:?}",
                    raw.display()
                )));
            }
        }
    }
    Ok(())
}

fn extract_zip(archive: &Path, ex: &mut Extractor<'_>) -> Result<(), ApiError> {
    let mut file = File::open(archive).map_err(internal(archive))?;
    let declared = zip_entry_count(&mut file)?;
    if declared > ex.limits.max_entries as u64 {
        return Err(ApiError::payload_too_large(format!(
            "the archive has {declared} entries, more than {} (limits.max_upload_entries)",
            ex.limits.max_entries
        )));
    }
    let bad = |e: zip::result::ZipError| ApiError::bad_request(format!("invalid zip archive: {e}"));
    let mut ar = zip::ZipArchive::new(BufReader::new(file)).map_err(bad)?;
    for i in 0..ar.len() {
        let mut entry = ar.by_index(i).map_err(bad)?;
        ex.count_entry()?;
        let name = entry.name().map_err(bad)?.into_owned();
        let rel = safe_relative_path(Path::new(&name))?;
        // The zip crate's own check as a second opinion (it also refuses NUL bytes).
        if entry.enclosed_name().is_none() {
            return Err(ApiError::bad_request(format!(
                "archive entry {name} leaves the archive"
            )));
        }
        if entry.is_symlink() {
            return Err(ApiError::bad_request(format!(
                "archive entry {name} is a link; links are not allowed"
            )));
        }
        if entry.is_dir() {
            ex.dir(&rel)?;
        } else {
            ex.file(&rel, &mut entry)?;
        }
    }
    Ok(())
}

/// A 400 for a dataset the pipeline cannot read (its message names files as the dataset does).
fn dataset_error(e: relfusion_core::Error) -> ApiError {
    match e {
        relfusion_core::Error::Dataset(message) => {
            ApiError::bad_request(format!("uploaded dataset: {message}"))
        }
        other => ApiError::bad_request(format!("uploaded dataset: {other}")),
    }
}

/// The entry count a zip's end-of-central-directory record declares (its zip64 record's when
/// the classic one says 0xFFFF), read from the file's tail alone: the central directory is not
/// parsed. A count that cannot fit the file (46 bytes per central entry) is a 400.
pub fn zip_entry_count(file: &mut File) -> Result<u64, ApiError> {
    use std::io::{Seek, SeekFrom};
    const EOCD: [u8; 4] = [0x50, 0x4b, 0x05, 0x06];
    const ZIP64_LOCATOR: [u8; 4] = [0x50, 0x4b, 0x06, 0x07];
    const ZIP64_EOCD: [u8; 4] = [0x50, 0x4b, 0x06, 0x06];
    let bad = |what: &str| ApiError::bad_request(format!("invalid zip archive: {what}"));
    let io = |e: std::io::Error| ApiError::bad_request(format!("invalid zip archive: {e}"));
    let len = file.seek(SeekFrom::End(0)).map_err(io)?;
    let tail_len = len.min(22 + 65535 + 20);
    let mut tail = vec![0u8; tail_len as usize];
    file.seek(SeekFrom::Start(len - tail_len)).map_err(io)?;
    file.read_exact(&mut tail).map_err(io)?;
    let at = (0..tail.len().saturating_sub(21))
        .rev()
        .find(|&i| tail[i..i + 4] == EOCD)
        .ok_or_else(|| bad("no end-of-central-directory record"))?;
    let le16 = |b: &[u8]| u64::from(u16::from_le_bytes([b[0], b[1]]));
    let mut count = le16(&tail[at + 10..at + 12]);
    if count == 0xFFFF && at >= 20 && tail[at - 20..at - 16] == ZIP64_LOCATOR {
        let mut off = [0u8; 8];
        off.copy_from_slice(&tail[at - 12..at - 4]);
        let offset = u64::from_le_bytes(off);
        if offset.saturating_add(56) > len {
            return Err(bad("zip64 record outside the file"));
        }
        let mut record = [0u8; 56];
        file.seek(SeekFrom::Start(offset)).map_err(io)?;
        file.read_exact(&mut record).map_err(io)?;
        if record[..4] != ZIP64_EOCD {
            return Err(bad("broken zip64 record"));
        }
        let mut n = [0u8; 8];
        n.copy_from_slice(&record[32..40]);
        count = u64::from_le_bytes(n);
    }
    if count.saturating_mul(46) > len {
        return Err(bad("it declares more entries than it can hold"));
    }
    file.seek(SeekFrom::Start(0)).map_err(io)?;
    Ok(count)
}

/// The dataset folder of an extracted upload: `dir` itself when it holds `rgb.txt`, else the
/// single first-level folder that does.
pub fn find_dataset_root(dir: &Path) -> Result<PathBuf, ApiError> {
    if dir.join("rgb.txt").is_file() {
        return Ok(dir.to_path_buf());
    }
    let mut found = Vec::new();
    let entries = std::fs::read_dir(dir).map_err(internal(dir))?;
    for entry in entries {
        let entry = entry.map_err(internal(dir))?;
        let path = entry.path();
        if path.is_dir() && path.join("rgb.txt").is_file() {
            found.push(path);
        }
    }
    match found.len() {
        1 => Ok(found.remove(0)),
        0 => Err(ApiError::bad_request(
            "no TUM-layout dataset in the archive: rgb.txt must be at its root or one folder down",
        )),
        n => Err(ApiError::bad_request(format!(
            "the archive holds {n} datasets (folders with rgb.txt); upload one at a time"
        ))),
    }
}

/// The whole staging of an upload (blocking): extracts `archive` into `staging`, finds the
/// dataset folder, moves the tree to `final_dir` (durably), and checks the dataset where it
/// will stay: `rgb.txt` parses, listed files exist, a camera resolves (`camera`, else
/// `calibration.txt`, else a TUM preset from the folder name) and the first image has its size.
pub fn stage_upload(
    archive: &Path,
    kind: ArchiveKind,
    staging: &Path,
    final_dir: &Path,
    limits: ExtractLimits,
    camera: Option<PinholeCamera>,
    check_camera: &dyn Fn(&PinholeCamera) -> Result<(), ApiError>,
) -> Result<Staged, ApiError> {
    let bytes = extract(archive, kind, staging, limits)?;
    let dataset_rel = find_dataset_root(staging)?
        .strip_prefix(staging)
        .map(Path::to_path_buf)
        .unwrap_or_default();
    std::fs::rename(staging, final_dir)
        .map_err(|e| ApiError::internal(format!("storing the upload: {e}")))?;
    if let Some(parent) = final_dir.parent() {
        sync_dir(parent).map_err(|e| ApiError::internal(e.to_string()))?;
    }
    let dir = final_dir.join(&dataset_rel);
    let mut seq =
        TumSequence::open_bounded(&dir, camera, limits.sequence).map_err(dataset_error)?;
    if let Some(camera) = camera {
        seq.camera = camera;
    }
    // Before any image is decoded: the camera (from calibration.txt, the first image's
    // header) may be larger than this server takes.
    check_camera(&seq.camera)?;
    seq.load_rgb(0).map_err(dataset_error)?;
    Ok(Staged {
        dataset_rel,
        camera: seq.camera,
        frames: seq.len(),
        bytes,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMITS: ExtractLimits = ExtractLimits {
        max_bytes: 1 << 20,
        max_entries: 100,
        sequence: SequenceLimits {
            max_frames: 100,
            max_text_bytes: 1 << 20,
            max_image_bytes: 1 << 20,
        },
    };

    fn temp(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("relfusion-upload-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).expect("temp");
        d
    }

    /// A tar with one entry whose raw name is written without the crate's own path checks.
    fn raw_tar(name: &str, entry_type: tar::EntryType, link: Option<&str>, data: &[u8]) -> Vec<u8> {
        let mut header = tar::Header::new_gnu();
        {
            let gnu = header.as_gnu_mut().expect("gnu");
            gnu.name[..name.len()].copy_from_slice(name.as_bytes());
        }
        header.set_entry_type(entry_type);
        header.set_size(data.len() as u64);
        header.set_mode(0o644);
        if let Some(target) = link {
            header.set_link_name(target).expect("link name");
        }
        header.set_cksum();
        let mut b = tar::Builder::new(Vec::new());
        b.append(&header, data).expect("append");
        b.into_inner().expect("finish")
    }

    fn extract_bytes(
        tag: &str,
        bytes: &[u8],
        kind: ArchiveKind,
    ) -> (Result<u64, ApiError>, PathBuf) {
        let dir = temp(tag);
        let archive = dir.join("a.bin");
        std::fs::write(&archive, bytes).expect("write");
        let dest = dir.join("out");
        (extract(&archive, kind, &dest, LIMITS), dir)
    }

    #[test]
    fn tar_extracts_a_dataset_one_level_down() {
        let mut b = tar::Builder::new(Vec::new());
        for (name, data) in [
            ("seq/rgb.txt", &b"0 rgb/0.png\n"[..]),
            ("seq/rgb/0.png", b"x"),
        ] {
            let mut h = tar::Header::new_gnu();
            h.set_size(data.len() as u64);
            h.set_mode(0o644);
            h.set_cksum();
            b.append_data(&mut h, name, data).expect("append");
        }
        let bytes = b.into_inner().expect("tar");
        let (r, dir) = extract_bytes("ok", &bytes, ArchiveKind::Tar);
        assert_eq!(r.expect("extract"), 13);
        let root = find_dataset_root(&dir.join("out")).expect("root");
        assert!(root.ends_with("seq"));
        assert_eq!(std::fs::read(root.join("rgb/0.png")).expect("file"), b"x");
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn tar_rejects_traversal_absolute_paths_and_links() {
        let cases = [
            ("../evil.txt", tar::EntryType::Regular, None, "leaves"),
            ("a/../../evil.txt", tar::EntryType::Regular, None, "leaves"),
            ("/tmp/evil.txt", tar::EntryType::Regular, None, "absolute"),
            ("link", tar::EntryType::Symlink, Some("/etc"), "link"),
            ("hard", tar::EntryType::Link, Some("/etc/passwd"), "link"),
        ];
        for (i, (name, ty, link, why)) in cases.into_iter().enumerate() {
            let bytes = raw_tar(name, ty, link, b"pwned");
            let (r, dir) = extract_bytes(&format!("bad{i}"), &bytes, ArchiveKind::Tar);
            let e = r.expect_err(name);
            assert_eq!(e.status, 400, "{name}: {e}");
            assert!(e.message.contains(why), "{name}: {e}");
            assert!(!dir.join("evil.txt").exists() && !Path::new("/tmp/evil.txt").exists());
            let _ = std::fs::remove_dir_all(dir);
        }
    }

    #[test]
    fn truncated_and_oversized_archives_are_refused() {
        let big = raw_tar(
            "big.bin",
            tar::EntryType::Regular,
            None,
            &vec![7u8; 2 << 20],
        );
        let (r, dir) = extract_bytes("big", &big, ArchiveKind::Tar);
        assert_eq!(r.expect_err("too big").status, 413);
        let _ = std::fs::remove_dir_all(dir);
        let ok = raw_tar("f.bin", tar::EntryType::Regular, None, &vec![1u8; 5000]);
        let (r, dir) = extract_bytes("trunc", &ok[..2048], ArchiveKind::Tar);
        assert_eq!(r.expect_err("truncated").status, 400);
        let _ = std::fs::remove_dir_all(dir);
        let (r, dir) = extract_bytes("notzip", b"not a zip at all", ArchiveKind::Zip);
        assert_eq!(r.expect_err("not zip").status, 400);
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn zip_extracts_and_rejects_traversal_and_symlinks() {
        use zip::write::SimpleFileOptions;
        let make = |entries: &[(&str, bool)]| {
            let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
            for (name, link) in entries {
                if *link {
                    w.add_symlink(*name, "/etc", SimpleFileOptions::default())
                        .expect("symlink");
                } else {
                    w.start_file(*name, SimpleFileOptions::default())
                        .expect("start");
                    w.write_all(b"data").expect("write");
                }
            }
            w.finish().expect("finish").into_inner()
        };
        let (r, dir) = extract_bytes("zipok", &make(&[("d/rgb.txt", false)]), ArchiveKind::Zip);
        assert_eq!(r.expect("zip"), 4);
        assert!(dir.join("out/d/rgb.txt").is_file());
        let _ = std::fs::remove_dir_all(dir);
        for (i, entries) in [
            vec![("../evil.txt", false)],
            vec![("/abs/evil.txt", false)],
            vec![("l", true)],
        ]
        .into_iter()
        .enumerate()
        {
            let (r, dir) = extract_bytes(&format!("zipbad{i}"), &make(&entries), ArchiveKind::Zip);
            assert_eq!(r.expect_err("unsafe zip").status, 400);
            let _ = std::fs::remove_dir_all(dir);
        }
    }

    #[test]
    fn dataset_root_must_be_unique() {
        let dir = temp("roots");
        std::fs::create_dir_all(dir.join("a")).expect("a");
        std::fs::create_dir_all(dir.join("b")).expect("b");
        assert!(find_dataset_root(&dir).is_err());
        std::fs::write(dir.join("a/rgb.txt"), "").expect("a");
        assert!(find_dataset_root(&dir).expect("one").ends_with("a"));
        std::fs::write(dir.join("b/rgb.txt"), "").expect("b");
        assert!(find_dataset_root(&dir).is_err());
        let _ = std::fs::remove_dir_all(dir);
    }
}

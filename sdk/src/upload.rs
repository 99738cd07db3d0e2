//! `POST /v1/uploads`: a TUM-layout dataset as a tar archive built on the fly.
//!
//! Nothing is staged on disk and the archive is never whole in memory: a blocking thread
//! writes the tar into a bounded channel of chunks that is the request body, so a multi-GB
//! sequence uploads in constant memory, and a slow server slows the tar writer rather than
//! filling RAM.
//!
//! The archive holds exactly what the server needs to run the sequence: `rgb.txt`, the images
//! it lists, `groundtruth.txt` when present, and a `calibration.txt`: the dataset's own, or
//! one written from the camera the client resolved (a caller override, else the TUM preset
//! recognised from the folder name), so the server sees the same intrinsics (distortion
//! included) that `relfusion run` would use. Depth images are left out: the pipeline is
//! monocular.

use std::collections::HashSet;
use std::io::{self, Write};
use std::path::{Component, Path, PathBuf};

use bytes::Bytes;
use relfusion_core::dataset::TumSequence;
use relfusion_core::geometry::PinholeCamera;
use tokio::sync::mpsc;

use crate::api::{Client, SessionInfo};
use crate::error::ClientError;

/// Size of the chunks the tar writer hands to the HTTP body.
const CHUNK: usize = 256 * 1024;
/// Chunks in flight between the tar writer and the socket (bounds memory to ~1 MiB).
const CHUNKS_IN_FLIGHT: usize = 4;

/// Upload options.
#[derive(Clone, Debug, Default)]
pub struct UploadOptions {
    /// Intrinsics to use instead of the dataset's own (written as its calibration.txt).
    pub camera: Option<PinholeCamera>,
}

/// One file of the archive.
#[derive(Clone, Debug, PartialEq)]
enum Source {
    File(PathBuf),
    Bytes(Vec<u8>),
}

/// What goes into the archive, in order.
#[derive(Clone, Debug)]
pub struct UploadPlan {
    /// The folder name inside the archive (the dataset folder's own name: the server
    /// recognises TUM cameras by it).
    pub root: String,
    entries: Vec<(String, Source)>,
    /// Sum of the file sizes (the archive is slightly larger: 512-byte headers and padding).
    pub payload_bytes: u64,
    /// Frames listed in rgb.txt.
    pub frames: usize,
}

impl UploadPlan {
    /// Plans the upload of the dataset in `dir` (opening it validates the layout locally,
    /// so a broken dataset fails before anything is sent).
    pub fn new(dir: &Path, opts: &UploadOptions) -> Result<Self, ClientError> {
        let seq = TumSequence::open(dir, opts.camera)?;
        // The dataset's calibration.txt wins inside `open`; an explicit override wins here.
        let camera = opts.camera.unwrap_or(seq.camera);
        let root = std::fs::canonicalize(dir)
            .ok()
            .and_then(|d| d.file_name().map(|n| n.to_string_lossy().into_owned()))
            .filter(|n| !n.is_empty())
            .unwrap_or_else(|| "dataset".to_string());
        let mut entries = vec![("rgb.txt".to_string(), Source::File(dir.join("rgb.txt")))];
        let mut seen = HashSet::new();
        for frame in &seq.frames {
            let rel = frame.rgb.strip_prefix(&seq.root).map_err(|_| {
                ClientError::InvalidOption(format!(
                    "{} lies outside the dataset folder",
                    frame.rgb.display()
                ))
            })?;
            let name = archive_name(rel).ok_or_else(|| {
                ClientError::InvalidOption(format!(
                    "rgb.txt entry {} must be a plain relative path inside the dataset",
                    rel.display()
                ))
            })?;
            if seen.insert(name.clone()) {
                entries.push((name, Source::File(frame.rgb.clone())));
            }
        }
        let gt = dir.join("groundtruth.txt");
        if gt.is_file() {
            entries.push(("groundtruth.txt".into(), Source::File(gt)));
        }
        let calib = dir.join("calibration.txt");
        let calibration = if opts.camera.is_none() && calib.is_file() {
            Source::File(calib)
        } else {
            Source::Bytes(calibration_txt(&camera).into_bytes())
        };
        entries.push(("calibration.txt".into(), calibration));
        let mut payload_bytes = 0;
        for (_, source) in &entries {
            payload_bytes += match source {
                Source::File(p) => std::fs::metadata(p)
                    .map_err(|e| ClientError::io(p, e))?
                    .len(),
                Source::Bytes(b) => b.len() as u64,
            };
        }
        Ok(Self {
            root,
            entries,
            payload_bytes,
            frames: seq.len(),
        })
    }

    /// The archive paths, in order.
    pub fn names(&self) -> Vec<String> {
        self.entries
            .iter()
            .map(|(n, _)| format!("{}/{n}", self.root))
            .collect()
    }

    /// Writes the whole tar archive into `out`, calling `on_bytes` with the running total of
    /// archive bytes written.
    pub fn write_tar<W: Write>(&self, out: W, on_bytes: impl FnMut(u64)) -> io::Result<()> {
        let mut builder = tar::Builder::new(Counting {
            inner: out,
            written: 0,
            on_bytes,
        });
        for (name, source) in &self.entries {
            let path = format!("{}/{name}", self.root);
            let mut header = tar::Header::new_gnu();
            header.set_entry_type(tar::EntryType::Regular);
            header.set_mode(0o644);
            header.set_mtime(0);
            match source {
                Source::File(p) => {
                    let file = std::fs::File::open(p)
                        .map_err(|e| io::Error::new(e.kind(), format!("{}: {e}", p.display())))?;
                    header.set_size(file.metadata()?.len());
                    builder.append_data(&mut header, &path, file)?;
                }
                Source::Bytes(b) => {
                    header.set_size(b.len() as u64);
                    builder.append_data(&mut header, &path, b.as_slice())?;
                }
            }
        }
        builder.into_inner()?.flush()
    }
}

/// Uploads the dataset in `dir`: the server answers once the archive is stored durably, with
/// the new upload session (processing then starts on the server; follow it with
/// [`Client::wait_finished`]). `on_bytes(sent, payload_bytes)` reports progress from the
/// archive writer's thread.
pub async fn upload_dataset(
    client: &Client,
    dir: &Path,
    opts: &UploadOptions,
    on_bytes: impl Fn(u64, u64) + Send + 'static,
) -> Result<SessionInfo, ClientError> {
    let plan = UploadPlan::new(dir, opts)?;
    let total = plan.payload_bytes;
    let (tx, mut rx) = mpsc::channel::<io::Result<Bytes>>(CHUNKS_IN_FLIGHT);
    let writer_tx = tx.clone();
    let writer = tokio::task::spawn_blocking(move || {
        let out = ChunkWriter {
            tx: writer_tx,
            buf: Vec::with_capacity(CHUNK),
        };
        let result = plan.write_tar(out, |n| on_bytes(n, total));
        if let Err(e) = &result {
            // Make the body fail, so the server sees a broken archive rather than a short one.
            let _ = tx.blocking_send(Err(io::Error::new(e.kind(), e.to_string())));
        }
        result
    });
    let body = futures_util::stream::poll_fn(move |cx| rx.poll_recv(cx));
    let answer = client
        .post_upload(
            reqwest::Body::wrap_stream(body),
            &[("format", "tar".to_string())],
        )
        .await;
    let written = writer
        .await
        .map_err(|e| ClientError::Protocol(format!("archive writer: {e}")))?;
    match (answer, written) {
        (Ok(info), Ok(())) => Ok(info),
        // The server's answer explains a refused upload better than the broken pipe it caused.
        (Err(e), _) => Err(e),
        (Ok(_), Err(e)) => Err(ClientError::io(dir, e)),
    }
}

/// `calibration.txt` for `camera`: `fx fy cx cy [k1 k2 p1 p2 k3]`, full precision.
pub fn calibration_txt(camera: &PinholeCamera) -> String {
    let mut line = format!("{} {} {} {}", camera.fx, camera.fy, camera.cx, camera.cy);
    if let Some(d) = camera.distortion {
        line.push_str(&format!(" {} {} {} {} {}", d.k1, d.k2, d.p1, d.p2, d.k3));
    }
    format!("# fx fy cx cy [k1 k2 p1 p2 k3] (written by relfusion upload)\n{line}\n")
}

/// `rel` as a `/`-separated archive path, if it only has normal components.
fn archive_name(rel: &Path) -> Option<String> {
    let mut parts = Vec::new();
    for c in rel.components() {
        match c {
            Component::Normal(s) => parts.push(s.to_str()?.to_string()),
            Component::CurDir => {}
            _ => return None,
        }
    }
    (!parts.is_empty()).then(|| parts.join("/"))
}

/// Counts what passes through, for progress.
struct Counting<W, F> {
    inner: W,
    written: u64,
    on_bytes: F,
}

impl<W: Write, F: FnMut(u64)> Write for Counting<W, F> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.written += n as u64;
        (self.on_bytes)(self.written);
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}

/// A `Write` that cuts what it gets into chunks for the request body; blocks while the
/// channel is full (back-pressure from the socket), fails once the request is gone.
struct ChunkWriter {
    tx: mpsc::Sender<io::Result<Bytes>>,
    buf: Vec<u8>,
}

impl ChunkWriter {
    fn send_buf(&mut self) -> io::Result<()> {
        if self.buf.is_empty() {
            return Ok(());
        }
        let chunk = Bytes::from(std::mem::replace(&mut self.buf, Vec::with_capacity(CHUNK)));
        self.tx
            .blocking_send(Ok(chunk))
            .map_err(|_| io::Error::new(io::ErrorKind::BrokenPipe, "the upload request ended"))
    }
}

impl Write for ChunkWriter {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let room = CHUNK - self.buf.len();
        let n = buf.len().min(room);
        self.buf.extend_from_slice(&buf[..n]);
        if self.buf.len() >= CHUNK {
            self.send_buf()?;
        }
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.send_buf()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny_dataset(dir: &Path, calibration: bool) {
        std::fs::create_dir_all(dir.join("rgb")).expect("mkdir");
        let img = image::RgbImage::from_pixel(16, 16, image::Rgb([10, 20, 30]));
        let mut rgb_txt = String::from("# timestamp filename\n");
        for i in 0..3 {
            let name = format!("rgb/{i}.png");
            img.save(dir.join(&name)).expect("write png");
            rgb_txt.push_str(&format!("{}.0 {name}\n", i));
        }
        std::fs::write(dir.join("rgb.txt"), rgb_txt).expect("rgb.txt");
        if calibration {
            std::fs::write(dir.join("calibration.txt"), "20 20 7.5 7.5\n").expect("calib");
        }
    }

    fn temp(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("relfusion-upload-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn the_archive_holds_the_sequence_under_its_folder_name() {
        let dir = temp("plan").join("my_seq");
        tiny_dataset(&dir, true);
        let plan = UploadPlan::new(&dir, &UploadOptions::default()).expect("plan");
        assert_eq!(
            plan.names(),
            [
                "my_seq/rgb.txt",
                "my_seq/rgb/0.png",
                "my_seq/rgb/1.png",
                "my_seq/rgb/2.png",
                "my_seq/calibration.txt"
            ]
        );
        let mut tar_bytes = Vec::new();
        let mut last = 0;
        plan.write_tar(&mut tar_bytes, |n| last = n).expect("tar");
        assert_eq!(last, tar_bytes.len() as u64);
        assert_eq!(tar_bytes.len() % 512, 0);
        let mut archive = tar::Archive::new(tar_bytes.as_slice());
        let mut names = Vec::new();
        for entry in archive.entries().expect("entries") {
            let mut entry = entry.expect("entry");
            let name = entry.path().expect("path").to_string_lossy().into_owned();
            let mut content = Vec::new();
            io::Read::read_to_end(&mut entry, &mut content).expect("read");
            if name.ends_with("calibration.txt") {
                assert_eq!(content, b"20 20 7.5 7.5\n");
            }
            if name.ends_with("0.png") {
                assert_eq!(content, std::fs::read(dir.join("rgb/0.png")).expect("png"));
            }
            names.push(name);
        }
        assert_eq!(names, plan.names());
        let _ = std::fs::remove_dir_all(dir.parent().expect("parent"));
    }

    #[test]
    fn an_overridden_camera_becomes_the_calibration() {
        let dir = temp("camera").join("seq");
        tiny_dataset(&dir, true);
        let camera = PinholeCamera::new(30.0, 31.0, 8.0, 7.0, 16, 16)
            .expect("camera")
            .with_distortion(relfusion_core::geometry::Distortion::new(
                0.1, -0.2, 0.0, 0.0, 0.3,
            ))
            .expect("distortion");
        let plan = UploadPlan::new(
            &dir,
            &UploadOptions {
                camera: Some(camera),
            },
        )
        .expect("plan");
        let (_, source) = plan.entries.last().expect("calibration entry");
        let Source::Bytes(text) = source else {
            panic!("a written calibration")
        };
        let text = String::from_utf8(text.clone()).expect("utf8");
        assert!(text.ends_with("30 31 8 7 0.1 -0.2 0 0 0.3\n"), "{text}");
        let _ = std::fs::remove_dir_all(dir.parent().expect("parent"));
    }

    #[test]
    fn archive_names_refuse_escapes() {
        assert_eq!(
            archive_name(Path::new("rgb/1.png")).as_deref(),
            Some("rgb/1.png")
        );
        assert_eq!(
            archive_name(Path::new("./rgb/1.png")).as_deref(),
            Some("rgb/1.png")
        );
        assert_eq!(archive_name(Path::new("../x.png")), None);
        assert_eq!(archive_name(Path::new("/etc/passwd")), None);
    }

    #[test]
    fn chunks_are_bounded_and_complete() {
        let (tx, mut rx) = mpsc::channel(64);
        let mut w = ChunkWriter {
            tx,
            buf: Vec::new(),
        };
        let data: Vec<u8> = (0..(CHUNK * 2 + 100)).map(|i| (i % 251) as u8).collect();
        w.write_all(&data).expect("write");
        w.flush().expect("flush");
        drop(w);
        let mut got = Vec::new();
        while let Ok(chunk) = rx.try_recv() {
            let chunk = chunk.expect("ok chunk");
            assert!(chunk.len() <= CHUNK);
            got.extend_from_slice(&chunk);
        }
        assert_eq!(got, data);
    }
}

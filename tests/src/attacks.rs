//! Hostile inputs the hardening tests send, built once here: decompression-bomb images, zip
//! bombs and entry floods, and a way to watch the server's memory.

use std::io::Write as _;

/// A PNG whose header claims `w`×`h` 8-bit grey pixels, with an empty image stream: what a
/// decompression-bomb frame looks like to a decoder (a few dozen bytes claiming gigabytes).
pub fn png_claiming(w: u32, h: u32) -> Vec<u8> {
    fn crc32(bytes: &[u8]) -> u32 {
        let mut crc = 0xffff_ffffu32;
        for &b in bytes {
            crc ^= u32::from(b);
            for _ in 0..8 {
                crc = if crc & 1 != 0 {
                    (crc >> 1) ^ 0xedb8_8320
                } else {
                    crc >> 1
                };
            }
        }
        !crc
    }
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let ihdr = [
        &w.to_be_bytes()[..],
        &h.to_be_bytes()[..],
        &[8, 0, 0, 0, 0][..],
    ]
    .concat();
    // A zlib stream of one empty stored block.
    let idat = vec![0x78, 0x01, 0x01, 0x00, 0x00, 0xff, 0xff, 0, 0, 0, 1];
    for (kind, data) in [(*b"IHDR", ihdr), (*b"IDAT", idat), (*b"IEND", Vec::new())] {
        out.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let mut chunk = kind.to_vec();
        chunk.extend_from_slice(&data);
        out.extend_from_slice(&chunk);
        out.extend_from_slice(&crc32(&chunk).to_be_bytes());
    }
    out
}

/// A zip of one member of `zeros` zero bytes (deflated: a zip bomb) followed by `entries`
/// empty members (an entry flood).
pub fn zip_archive(entries: usize, zeros: usize) -> Vec<u8> {
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let deflated = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    if zeros > 0 {
        zip.start_file("seq/rgb/bomb.png", deflated)
            .expect("zip entry");
        let chunk = vec![0u8; 1 << 20];
        for _ in 0..zeros >> 20 {
            zip.write_all(&chunk).expect("zip write");
        }
    }
    let stored =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for i in 0..entries {
        zip.start_file(format!("seq/f{i}"), stored)
            .expect("zip entry");
    }
    zip.finish().expect("zip").into_inner()
}

/// A tar of `(name, bytes)` entries, names written as given.
pub fn tar_of(entries: &[(&str, &[u8])]) -> Vec<u8> {
    let mut builder = tar::Builder::new(Vec::new());
    for (name, data) in entries {
        let mut header = tar::Header::new_gnu();
        header.set_size(data.len() as u64);
        header.set_mode(0o644);
        header.set_cksum();
        builder
            .append_data(&mut header, name, *data)
            .expect("tar entry");
    }
    builder.into_inner().expect("tar")
}

/// A TUM tar: `seq/rgb.txt` with `rgb_txt`, `seq/depth.txt` with `depth_txt` when given, a
/// 320×240 `seq/calibration.txt`, and `files` (names as given).
pub fn tum_tar(rgb_txt: &str, depth_txt: Option<&str>, files: &[(&str, &[u8])]) -> Vec<u8> {
    let mut entries: Vec<(&str, &[u8])> = vec![
        ("seq/rgb.txt", rgb_txt.as_bytes()),
        ("seq/calibration.txt", b"320 320 160 120\n"),
    ];
    if let Some(depth) = depth_txt {
        entries.push(("seq/depth.txt", depth.as_bytes()));
    }
    entries.extend_from_slice(files);
    tar_of(&entries)
}

/// A size field of `/proc/<pid>/status` (kB) in bytes (Linux; 0 when it cannot be read).
fn status_bytes(pid: u32, field: &str) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with(field))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

/// Resident memory of process `pid` in bytes.
pub fn rss(pid: u32) -> u64 {
    status_bytes(pid, "VmRSS:")
}

/// Peak resident memory of process `pid` so far in bytes.
pub fn peak_rss(pid: u32) -> u64 {
    status_bytes(pid, "VmHWM:")
}

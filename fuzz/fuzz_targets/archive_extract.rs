//! Upload extraction: arbitrary bytes as a tar or a zip either extract inside the destination,
//! within the limits, or are refused; nothing is ever written outside it.
#![no_main]

use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};

use libfuzzer_sys::fuzz_target;
use relfusion_server::session::upload::{ArchiveKind, ExtractLimits, extract};

static RUN: AtomicU64 = AtomicU64::new(0);

fn scratch() -> PathBuf {
    // tmpfs where there is one: extraction writes and fsyncs files.
    let base = ["/dev/shm", "/tmp"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.is_dir())
        .unwrap_or_else(std::env::temp_dir);
    base.join(format!("relfusion-fuzz-extract-{}", std::process::id()))
}

fuzz_target!(|data: &[u8]| {
    let Some((&selector, archive)) = data.split_first() else {
        return;
    };
    let kind = if selector & 1 == 0 { ArchiveKind::Tar } else { ArchiveKind::Zip };
    let root = scratch();
    let n = RUN.fetch_add(1, Ordering::Relaxed);
    let input = root.join(format!("in-{n}"));
    let dest = root.join(format!("out-{n}"));
    std::fs::create_dir_all(&root).expect("scratch");
    std::fs::write(&input, archive).expect("write input");
    let limits = ExtractLimits {
        max_bytes: 1 << 20,
        max_entries: 64,
        sequence: relfusion_slam::dataset::SequenceLimits {
            max_frames: 64,
            max_text_bytes: 1 << 20,
            max_image_bytes: 1 << 20,
        },
    };
    if let Ok(bytes) = extract(&input, kind, &dest, limits) {
        assert!(bytes <= limits.max_bytes);
    }
    // Nothing but the input and the destination may exist in the scratch folder.
    for entry in std::fs::read_dir(&root).expect("scratch") {
        let path = entry.expect("entry").path();
        assert!(path == input || path == dest, "extraction wrote {}", path.display());
    }
    let _ = std::fs::remove_dir_all(&dest);
    let _ = std::fs::remove_file(&input);
});

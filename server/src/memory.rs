//! The server's memory budget and what a session costs against it.
//!
//! The budget (`limits.memory_budget_mb`, by default three quarters of what the machine or
//! its cgroup gives the process) is split into equal shares, one per session slot
//! (`limits.max_sessions`), after the process's own base. A session's cost is a base that
//! scales with its camera's pixels plus a cost per keyframe of its map (keyframes are kept
//! for loop closure, re-integration and the final optimisation); its share therefore sets how
//! many keyframes its map may hold. A camera whose base alone does not fit a share is refused
//! before anything is allocated.
//!
//! The constants were measured with `relfusion run` on synthetic sequences (RSS against
//! keyframes; docs/tuning.md "Memory of a session"): a keyframe in full costs about 110 B
//! per pixel (34 MB at 640×480), but only the `backend.resident_keyframes` newest are held in
//! full (issue 37); the next `backend.held_keyframes` keep a compact form (colour image, depth
//! map by its estimates, descriptor) of under 20 B per pixel in memory, and every older one
//! spills that and its dense maps to the session's store (`session::spill`), keeping its
//! descriptor, pose and graph entries. The fusion keeps the inputs of re-integration up to
//! `fusion.keyframe_memory_mb` and its voxel blocks up to `fusion.resident_blocks`, and spills
//! older ones. With the DSO-class front end the odometry's own bound (its window thread's queue
//! of frames, its keyframes' samples and points: 168 MB at 640×480) joins the base. The
//! estimate below rounds each term up.

use crate::config::Limits;

const MIB: u64 = 1 << 20;

/// Process memory outside sessions: the GPU context (lavapipe's JIT and threads), the shared
/// depth model, the HTTP and Zenoh runtimes.
pub const PROCESS_BASE: u64 = 384 * MIB;

/// Bytes per camera pixel a session holds whatever its map: tracking pyramids, the current
/// keyframe's depth hypotheses and its propagation target, undistortion maps, queued frames.
const BASE_PER_PIXEL: u64 = 400;
/// Fixed part of a session: thread stacks, the back end, and (dense layer on) its GPU buffers
/// and the fusion's block pool as first allocated.
const BASE_FIXED: u64 = 64 * MIB;
const BASE_DENSE: u64 = 160 * MIB;
/// Bytes per camera pixel of one keyframe held in full (the session's working set): frame
/// pyramid and colour, semi-dense depth, tracking reference and constraint-search levels.
const RESIDENT_PER_PIXEL: u64 = 160;
/// Bytes per camera pixel of a keyframe held in compact form.
const COMPACT_PER_PIXEL: u64 = 24;
/// Bytes of every older keyframe, spilled to the store, and per camera pixel of it: its
/// descriptor, graph vertex and edges, the fusion's record of it, the records of the frames
/// tracked against it, and the heap the allocator keeps around them. Measured in a 40-minute
/// `bench long` at 640×480 (docs/tuning.md, "The checkpoint's point cloud off the frame path"):
/// once the fusion inputs had reached their cap, RSS rose 0.09 MB a keyframe from minute 10
/// to 40; heaptrack found 17 kB a keyframe of live heap. 64 KiB + 1 B a pixel is 0.37 MB at
/// 640×480, four times the rise. (0.92 MB was charged before: the rise measured then was the
/// fusion inputs filling up, which `FUSION_INPUT_PER_DENSE_PIXEL` charges up to their cap.)
const KEYFRAME_FIXED: u64 = 64 * 1024;
const KEYFRAME_PER_PIXEL: u64 = 1;
/// Bytes per dense pixel of a fusion input held for re-integration (depth, weight, colour),
/// up to `fusion.keyframe_memory_mb`.
const FUSION_INPUT_PER_DENSE_PIXEL: u64 = 12;
/// Building a checkpoint's point cloud: about a quarter of a keyframe's pixels are semi-dense
/// points, 32 B each with their PLY bytes, up to `session::engine::POINTCLOUD_MAX_POINTS`.
const POINTCLOUD_PER_PIXEL: u64 = 8;
const POINTCLOUD_CAP: u64 = 128 * MIB;
/// Voxel blocks one keyframe adds to the fusion: the most the shared sequences fill per
/// keyframe is about 240 (fr1/rpy 0-249: 6852 blocks in 29 keyframes; redkitchen about 100;
/// docs/tuning.md "Bounded fusion"), rounded up.
const FUSION_BLOCKS_PER_KEYFRAME: u64 = 256;
/// Memory of one resident block: its voxels (6 KiB) and mesh (about 2 KiB) in the fusion, both
/// counted twice because a re-integration pass evicts only past twice `fusion.resident_blocks`
/// and the pool keeps its high water; and its mesh in the session's copy (about 2 KiB,
/// `session::mesh_state`, bounded by the same figure).
const FUSION_BYTES_PER_BLOCK: u64 = 2 * (6 + 2) * 1024 + 2 * 1024;

/// Fewest keyframes a session's share must hold for the session to be worth starting.
pub const MIN_KEYFRAMES: usize = 16;

/// What one session costs: `base + per_keyframe · n + min(input · n, input_cap)` for a map
/// of `n` keyframes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SessionCost {
    pub base: u64,
    pub per_keyframe: u64,
    /// What grows with the keyframes only up to `input_cap`: the fusion inputs held for
    /// re-integration (`fusion.keyframe_memory_mb`), the fusion's resident blocks and their
    /// meshes (`fusion.resident_blocks`) and the checkpoint's point cloud. Charged as it grows
    /// rather than up front, so a small share still holds a short map.
    pub input: u64,
    pub input_cap: u64,
}

/// What a session's map is made of, for [`SessionCost::estimate`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MapShape {
    /// Camera pixels.
    pub pixels: u64,
    /// Dense-layer pixels (`None`: the dense layer is off).
    pub dense_pixels: Option<u64>,
    /// Keyframes held in full (`backend.resident_keyframes`) and compact
    /// (`backend.held_keyframes`).
    pub resident: usize,
    pub held: usize,
    /// `fusion.keyframe_memory_mb` in bytes (`None`: no fusion).
    pub fusion_inputs: Option<u64>,
    /// `fusion.resident_blocks`: the voxel blocks the fusion keeps in memory.
    pub fusion_blocks: u64,
    /// With the DSO-class front end (`pipeline.frontend = "dso"`): the most its odometry
    /// holds beyond the keyframes (`relfusion_slam::odometry::memory::memory_bound`: the
    /// window thread's queue of frames, the window's samples and points), part of the base.
    pub odometry: Option<u64>,
}

impl SessionCost {
    /// The estimate for a map of `shape`; every keyframe past the working set is spilled.
    pub fn estimate(shape: MapShape) -> Self {
        let dense = shape.dense_pixels.unwrap_or(0);
        let working =
            RESIDENT_PER_PIXEL * shape.resident as u64 + COMPACT_PER_PIXEL * shape.held as u64;
        let fused = shape.fusion_inputs.is_some() && shape.dense_pixels.is_some();
        Self {
            base: BASE_FIXED
                + (BASE_PER_PIXEL + working) * shape.pixels
                + if shape.dense_pixels.is_some() {
                    BASE_DENSE
                } else {
                    0
                }
                + shape.odometry.unwrap_or(0),
            per_keyframe: KEYFRAME_FIXED + KEYFRAME_PER_PIXEL * shape.pixels,
            input: POINTCLOUD_PER_PIXEL * shape.pixels
                + if fused {
                    FUSION_INPUT_PER_DENSE_PIXEL * dense
                        + FUSION_BLOCKS_PER_KEYFRAME * FUSION_BYTES_PER_BLOCK
                } else {
                    0
                },
            input_cap: POINTCLOUD_CAP
                + if fused {
                    shape.fusion_inputs.unwrap_or(0) + shape.fusion_blocks * FUSION_BYTES_PER_BLOCK
                } else {
                    0
                },
        }
    }

    /// Memory of a map of `keyframes`.
    pub fn at(&self, keyframes: usize) -> u64 {
        let n = keyframes as u64;
        self.base + self.per_keyframe * n + (self.input * n).min(self.input_cap)
    }

    /// The most keyframes whose map fits in `bytes`.
    fn keyframes_within(&self, bytes: u64) -> u64 {
        let room = bytes.saturating_sub(self.base);
        let per = self.per_keyframe.max(1);
        // Past the cap a keyframe costs only its own part; before it, its input too.
        let past_cap = room.saturating_sub(self.input_cap) / per;
        if self.input == 0 || past_cap.saturating_mul(self.input) >= self.input_cap {
            past_cap
        } else {
            room / (per + self.input)
        }
    }
}

/// The budget and each session slot's share of it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MemoryPlan {
    /// Everything the server may use, in bytes.
    pub budget: u64,
    /// One session slot's share.
    pub share: u64,
    /// `limits.max_keyframes` (0 = as many as the share holds).
    max_keyframes: usize,
}

impl MemoryPlan {
    /// The plan for `limits` on this machine.
    pub fn new(limits: &Limits) -> Self {
        let budget = match limits.memory_budget_mb {
            0 => available_memory().saturating_mul(3) / 4,
            mb => mb.saturating_mul(MIB),
        };
        let share = budget.saturating_sub(PROCESS_BASE) / limits.max_sessions.max(1) as u64;
        Self {
            budget,
            share,
            max_keyframes: limits.max_keyframes,
        }
    }

    /// How many keyframes a session of `cost` may hold: what its share takes, capped by
    /// `limits.max_keyframes`; `Err` with the reason when fewer than [`MIN_KEYFRAMES`] fit.
    pub fn keyframes_for(&self, cost: SessionCost) -> Result<usize, String> {
        let fits = usize::try_from(cost.keyframes_within(self.share)).unwrap_or(usize::MAX);
        let allowed = match self.max_keyframes {
            0 => fits,
            n => n.min(fits),
        };
        if allowed < MIN_KEYFRAMES {
            return Err(format!(
                "a session of this camera needs {} MiB for a map of {MIN_KEYFRAMES} keyframes; \
                 each of this server's {} MiB session shares holds {allowed} (limits.\
                 memory_budget_mb / limits.max_sessions): use a smaller image",
                cost.at(MIN_KEYFRAMES) / MIB,
                self.share / MIB
            ));
        }
        Ok(allowed)
    }
}

/// Memory the machine gives this process: the smaller of physical memory and the cgroup's
/// limit (containers).
pub fn available_memory() -> u64 {
    let physical = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| {
            text.lines()
                .find(|l| l.starts_with("MemTotal:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<u64>().ok())
        })
        .map_or(8 << 30, |kb| kb * 1024);
    let cgroup = [
        "/sys/fs/cgroup/memory.max",
        "/sys/fs/cgroup/memory/memory.limit_in_bytes",
    ]
    .iter()
    .filter_map(|p| std::fs::read_to_string(p).ok())
    .filter_map(|s| s.trim().parse::<u64>().ok())
    .min();
    cgroup.map_or(physical, |c| c.min(physical))
}

/// Blocks at least this large that no free span of an arena fits are mapped on their own and
/// unmapped when freed. glibc raises this threshold to each mapped block freed (up to 32 MB),
/// so the session's growing transients grew the arenas and left free spans behind; 4 MB keeps
/// the per-frame images in the arenas (128 kB cost frames). docs/tuning.md, issue 37,
/// thirty-second stop.
pub const MMAP_THRESHOLD_BYTES: usize = 4 << 20;

/// Sets glibc's allocator for a long-running server: large blocks always mapped on their own
/// ([`MMAP_THRESHOLD_BYTES`]). Left as it is when `MALLOC_MMAP_THRESHOLD_` is in the
/// environment (glibc reads it itself), and elsewhere than glibc. Call once, early.
pub fn configure_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    if std::env::var_os("MALLOC_MMAP_THRESHOLD_").is_none() {
        #[allow(unsafe_code)]
        // SAFETY: `mallopt` takes two integers and only sets the allocator's parameters.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES as libc::c_int);
        }
    }
}

/// Hands the heap's free pages back to the system. glibc keeps what threads free in their
/// arenas: in a 640×480 session of 255 keyframes half the server's RSS (1.4 of 2.8 GB) was
/// such free memory (docs/tuning.md, "third stage"), which the budget and `/healthz` count as
/// used. Called after each checkpoint and by [`spawn_trimmer`]; a no-op elsewhere than glibc.
pub fn release_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        #[allow(unsafe_code)]
        // SAFETY: `malloc_trim` takes an integer and only walks the allocator's own lists.
        unsafe {
            libc::malloc_trim(0);
        }
    }
}

/// Runs [`release_free_memory`] every `every` on the blocking pool (the walk of the arenas
/// never holds a runtime thread), until the task is aborted; `None` when `every` is zero
/// (`limits.memory_trim_interval_s`). The trims after checkpoints alone let freed pages that
/// threads touch again pile up between checkpoints (docs/tuning.md, issue 37).
pub fn spawn_trimmer(every: std::time::Duration) -> Option<tokio::task::JoinHandle<()>> {
    if every.is_zero() {
        return None;
    }
    Some(tokio::spawn(async move {
        let mut tick = tokio::time::interval(every);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        tick.tick().await;
        loop {
            tick.tick().await;
            let started = std::time::Instant::now();
            if tokio::task::spawn_blocking(release_free_memory)
                .await
                .is_ok()
            {
                tracing::debug!(
                    elapsed_ms = started.elapsed().as_secs_f64() * 1e3,
                    "free memory released"
                );
            }
        }
    }))
}

/// Bytes the program holds from the heap (glibc's `mallinfo2`: in use in the arenas plus chunks
/// mapped on their own, touched or not), for metrics. Beside the resident memory it tells the
/// program's own growth from the rest: code, thread stacks, the libraries' mappings and what
/// the allocator keeps of freed memory (docs/tuning.md, issue 37). `None` elsewhere than
/// glibc. Walks the arenas' free lists: for scrapes, not per frame.
pub fn heap_in_use_bytes() -> Option<u64> {
    heap().map(|h| h.in_use)
}

/// Bytes free in the heap's arenas (glibc's `mallinfo2().fordblks`), for metrics: what the
/// allocator holds beyond [`heap_in_use_bytes`]. An upper bound of that share of RSS, since
/// [`release_free_memory`] hands whole free pages back while they still count here; its
/// growth beside a steady heap is fragmentation. `None` elsewhere than glibc.
pub fn heap_free_bytes() -> Option<u64> {
    heap().map(|h| h.free)
}

struct Heap {
    in_use: u64,
    free: u64,
}

fn heap() -> Option<Heap> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        #[allow(unsafe_code)]
        // SAFETY: `mallinfo2` takes nothing and returns a plain struct of counters.
        let info = unsafe { libc::mallinfo2() };
        Some(Heap {
            in_use: (info.uordblks + info.hblkhd) as u64,
            free: info.fordblks as u64,
        })
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    None
}

/// The process's resident memory in bytes (Linux), for metrics and health.
pub fn resident_bytes() -> Option<u64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    Some(pages * 4096)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits(budget_mb: u64, max_sessions: usize, max_keyframes: usize) -> Limits {
        Limits {
            memory_budget_mb: budget_mb,
            max_sessions,
            max_keyframes,
            ..Limits::default()
        }
    }

    #[tokio::test]
    async fn trimmer_is_off_at_zero_and_runs_until_aborted() {
        assert!(spawn_trimmer(std::time::Duration::ZERO).is_none());
        let task = spawn_trimmer(std::time::Duration::from_millis(20)).expect("on");
        tokio::time::sleep(std::time::Duration::from_millis(120)).await;
        assert!(!task.is_finished(), "the trimmer stopped on its own");
        task.abort();
        assert!(task.await.expect_err("aborted").is_cancelled());
    }

    #[test]
    fn shares_set_the_map_size_and_large_cameras_are_refused() {
        let plan = MemoryPlan::new(&limits(16 * 1024, 4, 0));
        let shape = |pixels: u64, dense: Option<u64>| MapShape {
            pixels,
            dense_pixels: dense,
            resident: 8,
            held: 24,
            fusion_inputs: Some(512 * MIB),
            fusion_blocks: 16384,
            odometry: None,
        };
        let vga = SessionCost::estimate(shape(640 * 480, Some(320 * 240)));
        let qvga = SessionCost::estimate(shape(320 * 240, Some(320 * 240)));
        let vga_kf = plan.keyframes_for(vga).expect("fits");
        let qvga_kf = plan.keyframes_for(qvga).expect("fits");
        assert!(
            vga_kf >= MIN_KEYFRAMES && qvga_kf > vga_kf,
            "{vga_kf} {qvga_kf}"
        );
        // Spilled keyframes cost neither their images nor their dense maps, and the fusion's
        // inputs stop at their cap: without the dense layer a share holds thousands.
        let sparse = SessionCost::estimate(shape(640 * 480, None));
        assert!(plan.keyframes_for(sparse).expect("fits") > 5000);
        assert!(vga.at(vga_kf) <= plan.share, "the map fits its share");
        assert!(vga.at(vga_kf + 1) > plan.share, "and uses it");
        // Before the cap each keyframe also costs its fusion input.
        assert_eq!(vga.at(10) - vga.at(9), vga.per_keyframe + vga.input);
        assert_eq!(vga.at(100_000) - vga.at(99_999), vga.per_keyframe);
        let huge = SessionCost::estimate(shape(8192 * 8192, Some(320 * 240)));
        let e = plan.keyframes_for(huge).expect_err("8192² does not fit");
        assert!(e.contains("smaller image"), "{e}");
        let capped = MemoryPlan::new(&limits(16 * 1024, 4, 20));
        assert_eq!(capped.keyframes_for(qvga), Ok(20));
    }

    /// The DSO-class front end's odometry is charged in the base: its share holds fewer
    /// keyframes, and a share that just holds an LSD session's smallest map refuses it.
    #[test]
    fn the_odometry_window_is_charged_in_the_base() {
        use relfusion_slam::odometry::{OdometryConfig, memory::memory_bound};
        let window = memory_bound(&OdometryConfig::default(), 640, 480);
        let shape = |odometry: Option<u64>| MapShape {
            pixels: 640 * 480,
            dense_pixels: Some(320 * 240),
            resident: 8,
            held: 24,
            fusion_inputs: Some(512 * MIB),
            fusion_blocks: 16384,
            odometry,
        };
        let lsd = SessionCost::estimate(shape(None));
        let dso = SessionCost::estimate(shape(Some(window)));
        assert_eq!(dso.base, lsd.base + window);
        assert_eq!(dso.per_keyframe, lsd.per_keyframe);
        let plan = MemoryPlan::new(&limits(2 * 1024, 1, 0));
        let (a, b) = (
            plan.keyframes_for(lsd).expect("fits"),
            plan.keyframes_for(dso).expect("fits"),
        );
        assert!(b < a, "{b} keyframes with the window, {a} without");
        assert!(dso.at(b) <= plan.share);
        let tight = MemoryPlan::new(&limits(
            (PROCESS_BASE + lsd.at(MIN_KEYFRAMES)) / MIB + 1,
            1,
            0,
        ));
        assert!(tight.keyframes_for(lsd).is_ok());
        assert!(tight.keyframes_for(dso).is_err());
    }

    #[test]
    fn the_fusion_is_charged_as_its_blocks_grow_up_to_their_bound() {
        let shape = |blocks: u64| MapShape {
            pixels: 320 * 240,
            dense_pixels: Some(320 * 240),
            resident: 8,
            held: 0,
            fusion_inputs: Some(512 * MIB),
            fusion_blocks: blocks,
            odometry: None,
        };
        let default = SessionCost::estimate(shape(16384));
        let small = SessionCost::estimate(shape(1024));
        // The same while the blocks grow; the bound sets the cap, so past it a map of many
        // keyframes costs more with a larger pool.
        assert_eq!(default.at(10), small.at(10));
        assert!(default.at(5000) - small.at(5000) >= 15 * 1024 * 18 * 1024);
        // A small share (the service test's: 964 MiB, one session) still holds a short map,
        // where charging the whole pool up front refused it (35 keyframes; 36 before the
        // fusion was charged at all).
        let plan = MemoryPlan::new(&limits(964, 1, 0));
        let n = plan.keyframes_for(default).expect("fits");
        assert!(n >= 32, "{n}");
        let on_a_large_machine = MemoryPlan::new(&limits(16 * 1024, 4, 0));
        let many = on_a_large_machine.keyframes_for(default).expect("fits");
        assert!(default.at(many) <= on_a_large_machine.share);
        assert!(
            default.at(many) >= default.base + default.input_cap,
            "past the cap"
        );
    }

    #[test]
    fn the_machine_reports_memory() {
        assert!(available_memory() > 256 * MIB);
        assert!(resident_bytes().is_some_and(|b| b > 0));
        #[cfg(all(target_os = "linux", target_env = "gnu"))]
        {
            // Zeroed, so mapped but never touched; the other tests' threads may free some of
            // theirs meanwhile, hence the margin.
            let before = heap_in_use_bytes().expect("glibc");
            let block = vec![0u8; 256 * MIB as usize];
            let during = heap_in_use_bytes().expect("glibc");
            drop(std::hint::black_box(block));
            assert!(during >= before + 192 * MIB, "{before} → {during}");
            assert!(heap_free_bytes().is_some());
        }
        let derived = MemoryPlan::new(&limits(0, 4, 0));
        assert!(derived.budget <= available_memory());
    }

    /// glibc raises its mapping threshold to each mapped block freed: without the fixed one, a
    /// 24 MB block after a 30 MB one was freed grows the arena, which then keeps that span. The
    /// threshold decides only when no free span of the arena fits, so the probe runs in a
    /// process of its own (this binary, this one test), whose arena is fresh.
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    #[test]
    fn large_blocks_stay_mapped_after_larger_ones_are_freed() {
        const PROBE: &str = "RELFUSION_MAPPING_PROBE";
        let name = "memory::tests::large_blocks_stay_mapped_after_larger_ones_are_freed";
        if std::env::var_os(PROBE).is_none() {
            let run = |configure: &str| {
                let out = std::process::Command::new(std::env::current_exe().expect("test binary"))
                    .args(["--exact", name, "--nocapture", "--test-threads", "1"])
                    .env(PROBE, configure)
                    .env_remove("MALLOC_MMAP_THRESHOLD_")
                    .output()
                    .expect("probe process");
                let text = String::from_utf8_lossy(&out.stdout).into_owned();
                assert!(out.status.success(), "{text}");
                text.lines()
                    .find_map(|l| l.split("mapped: ").nth(1))
                    .map(|v| v.trim_start().starts_with("true"))
                    .unwrap_or_else(|| panic!("no probe line: {text}"))
            };
            assert!(
                run("1"),
                "with the fixed threshold a 24 MB block came from an arena"
            );
            // The probe can tell: with glibc's own threshold the same block grows the arena.
            assert!(
                !run("0"),
                "with glibc's defaults the probe saw a mapped block"
            );
            return;
        }
        if std::env::var_os(PROBE).is_some_and(|v| v == "1") {
            configure_allocator();
        }
        #[allow(unsafe_code)]
        // SAFETY: plain malloc/free of blocks this test owns; the word before a block is its
        // chunk's size field in glibc, whose bit 1 marks a chunk mapped on its own.
        let mapped = unsafe {
            // Opaque, or the compiler drops a block that is only freed.
            let larger = std::hint::black_box(libc::malloc(30 << 20));
            assert!(!larger.is_null());
            libc::free(larger);
            let block = std::hint::black_box(libc::malloc(24 << 20)).cast::<usize>();
            assert!(!block.is_null());
            let mapped = block.sub(1).read() & 2 != 0;
            libc::free(block.cast());
            mapped
        };
        println!("mapped: {mapped}");
    }
}

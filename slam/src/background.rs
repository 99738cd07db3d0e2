//! Background threads give way to the frame path.
//!
//! Bounded queues make sure tracking never *waits* for the dense layer (issue 4: "the depth
//! prior never blocks tracking"), but on a machine with few cores the network, the lavapipe
//! kernels, the fusion and the back end's constraint work still take CPU time from it. Linux
//! nice values order them: the frame path (tracking, mapping) at normal priority, the back end
//! (keyframe constraints, pose graph) at [`Priority::Graph`], and the dense layer, the network
//! and the fusion at [`Priority::Dense`], the lowest, so that a keyframe's constraints are
//! ready before its densification competes with them. A dense layer that falls too far behind
//! skips keyframes through its bounded queue (counted); it never delays frames.
//!
//! Measured on 7-Scenes redkitchen (release, 2 cores, PyDNet++, `relfusion bench slam`, runs
//! alternating with and without the dense layer): tracking took +31 % with the dense layer on
//! when everything ran at normal priority (6.4 → 8.4 ms per frame); +24 % with only the dense
//! and fusion threads lowered (the network's pool thread was still started at normal priority);
//! +4.5 % with the back end at nice 19 too, whose backlog at `finish` then grew from 2.5 to 6 s;
//! and +3 % over six pairs of runs (6.59 → 6.79 ms) with the back end at nice 10 (backlog 3.3 s,
//! 19–20 of 24 keyframes densified while the frames run unpaced).

/// How far a background thread steps back from the frame path.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Priority {
    /// The back end: asynchronous, but its poses and loop closures are wanted within a few
    /// keyframes (nice 10).
    Graph,
    /// The dense layer, the depth network and the fusion: the lowest priority (nice 19).
    Dense,
}

impl Priority {
    fn nice(self) -> i32 {
        match self {
            Self::Graph => 10,
            Self::Dense => 19,
        }
    }
}

/// Lowers the calling thread's scheduling priority (and that of threads it starts later). Where
/// that is not possible the thread keeps its priority; that is logged, not an error.
pub fn lower_current_thread_priority(priority: Priority) {
    #[cfg(target_os = "linux")]
    {
        // On Linux `setpriority(PRIO_PROCESS, 0, …)` sets the nice value of the calling thread
        // only: threads are scheduled entities with their own nice value (setpriority(2),
        // BUGS), and threads they create inherit it.
        #[allow(unsafe_code)]
        // SAFETY: a system call with integer arguments only; no memory is passed or shared.
        let rc = unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, priority.nice()) };
        if rc != 0 {
            tracing::debug!(
                error = %std::io::Error::last_os_error(),
                "background thread keeps its priority"
            );
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = priority;
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    #[test]
    fn background_threads_run_at_their_priority_and_others_do_not() {
        let nice = |path: &str| -> i64 {
            // Field 19 of /proc/…/stat is the nice value; the command name (field 2) is in
            // parentheses and may hold spaces, so count from the last ')'.
            let stat = std::fs::read_to_string(path).expect("stat");
            let rest = &stat[stat.rfind(')').expect("comm") + 2..];
            rest.split(' ')
                .nth(16)
                .expect("nice")
                .parse()
                .expect("number")
        };
        let before = nice("/proc/thread-self/stat");
        for (priority, expected) in [(super::Priority::Graph, 10), (super::Priority::Dense, 19)] {
            let inside = std::thread::spawn(move || {
                super::lower_current_thread_priority(priority);
                let own = nice("/proc/thread-self/stat");
                let child = std::thread::spawn(move || nice("/proc/thread-self/stat"))
                    .join()
                    .expect("child");
                (own, child)
            })
            .join()
            .expect("thread");
            assert_eq!(
                inside,
                (expected, expected),
                "{priority:?}: lowered, and inherited by its threads"
            );
        }
        assert_eq!(
            nice("/proc/thread-self/stat"),
            before,
            "the caller is untouched"
        );
    }
}

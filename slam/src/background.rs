//! Background threads (the dense layer, the fusion, the server's GPU pool) give way to the
//! frame path.
//!
//! Bounded queues make sure tracking never *waits* for the dense layer (issue 4: "the depth
//! prior never blocks tracking"), but on a machine with few cores the network, the lavapipe
//! kernels and the fusion still take CPU time from it. At the lowest priority (Linux nice 19)
//! the scheduler gives tracking the CPU first and the background work takes what is left; a
//! dense layer that falls too far behind skips keyframes through its bounded queue (counted),
//! it never delays frames. Measured on 7-Scenes redkitchen (release, 2 cores, PyDNet++,
//! `relfusion bench slam --runs 2`): tracking 6.5–6.9 ms per frame with the dense layer off,
//! 13.0–13.5 with it on at normal priority, 8.2–9.2 at nice 19 (23–24 of 24 keyframes
//! densified). What remains is the network's second ONNX Runtime thread, created with the
//! session at normal priority, and the back end's extra constraint work for refined depth.

/// Nice value of background threads: the lowest priority.
const BACKGROUND_NICE: i32 = 19;

/// Lowers the calling thread's scheduling priority (and that of threads it starts later). Where
/// that is not possible the thread keeps its priority; that is logged, not an error.
pub fn lower_current_thread_priority() {
    #[cfg(target_os = "linux")]
    {
        // On Linux `setpriority(PRIO_PROCESS, 0, …)` sets the nice value of the calling thread
        // only: threads are scheduled entities with their own nice value (setpriority(2),
        // BUGS), and threads they create inherit it.
        #[allow(unsafe_code)]
        // SAFETY: a system call with integer arguments only; no memory is passed or shared.
        let rc = unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, BACKGROUND_NICE) };
        if rc != 0 {
            tracing::debug!(
                error = %std::io::Error::last_os_error(),
                "background thread keeps its priority"
            );
        }
    }
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    #[test]
    fn background_threads_run_at_the_lowest_priority_and_others_do_not() {
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
        let inside = std::thread::spawn(move || {
            super::lower_current_thread_priority();
            let own = nice("/proc/thread-self/stat");
            let child = std::thread::spawn(move || nice("/proc/thread-self/stat"))
                .join()
                .expect("child");
            (own, child)
        })
        .join()
        .expect("thread");
        assert_eq!(inside, (19, 19), "lowered, and inherited by its threads");
        assert_eq!(
            nice("/proc/thread-self/stat"),
            before,
            "the caller is untouched"
        );
    }
}

//! Tests of the generic background [`Worker`] and [`Link`] with a toy service.

use super::*;

/// Doubles numbers; replies once per job, and once more (the batch size) per batch; fails on
/// a negative number.
#[derive(Debug, Default)]
struct Doubler {
    batches: Vec<usize>,
    closed: bool,
}

impl Service for Doubler {
    type Job = i64;
    type Reply = i64;
    const BATCH: bool = true;

    fn handle(&mut self, jobs: Vec<i64>, reply: &mut dyn FnMut(i64)) -> Result<()> {
        self.batches.push(jobs.len());
        for job in jobs {
            if job < 0 {
                return Err(Error::Config(format!("negative job {job}")));
            }
            reply(2 * job);
        }
        Ok(())
    }

    fn close(&mut self, reply: &mut dyn FnMut(i64)) -> Result<()> {
        self.closed = true;
        reply(-1);
        Ok(())
    }

    fn unavailable(job: i64, _error: &str) -> Option<i64> {
        Some(-job)
    }
}

const SPEC: WorkerSpec = WorkerSpec {
    name: "test",
    priority: Priority::Dense,
    queue: 4,
};

#[test]
fn in_step_and_threaded_links_give_the_same_replies() {
    for threaded in [false, true] {
        let mut link = Link::new(threaded, SPEC, || Ok(Doubler::default())).expect("link");
        assert_eq!(link.is_threaded(), threaded);
        for job in 1..=3 {
            link.send(job).expect("queued");
        }
        let mut replies = link.finish().expect("finish");
        replies.retain(|&r| r != -1);
        assert_eq!(replies, vec![2, 4, 6], "threaded: {threaded}");
        let service = link.service().expect("the service after finish");
        assert!(service.closed);
        assert_eq!(service.batches.iter().sum::<usize>(), 3);
        assert!(link.submit(4).is_err(), "no job after finish");
    }
}

#[test]
fn errors_are_the_callers_in_step_and_recorded_on_a_thread() {
    let mut link = Link::new(false, SPEC, || Ok(Doubler::default())).expect("link");
    assert!(link.submit(-5).is_err());
    let mut worker = Worker::spawn(SPEC, || Ok(Doubler::default())).expect("worker");
    worker.send(-5).expect("queued");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    while worker.handled() < 1 && std::time::Instant::now() < deadline {
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    worker.send(7).expect("queued");
    let (replies, _) = worker.finish();
    assert!(replies.contains(&14), "the thread goes on after an error");
    assert!(worker.last_error().is_some_and(|e| e.contains("negative")));
}

#[test]
fn a_service_that_cannot_start_answers_every_job() {
    let mut worker =
        Worker::<Doubler>::spawn(SPEC, || Err(Error::Gpu("no adapter".into()))).expect("thread");
    worker.send(3).expect("queued");
    let (replies, service) = worker.finish();
    assert_eq!(replies, vec![-3]);
    assert!(service.is_none());
    assert!(
        worker
            .last_error()
            .is_some_and(|e| e.contains("no adapter"))
    );
}

#[test]
fn a_full_queue_refuses_without_waiting_and_batches_what_waited() {
    let gate = Arc::new(Mutex::new(()));
    let held = gate.lock().expect("gate");
    let thread_gate = gate.clone();
    let worker = Worker::spawn(SPEC, move || {
        // The service starts only once the test lets it: jobs pile up meanwhile.
        drop(thread_gate.lock());
        Ok(Doubler::default())
    })
    .expect("worker");
    let accepted = (0..10).filter(|&i| worker.submit(i).expect("open")).count();
    assert_eq!(
        accepted, SPEC.queue,
        "the bounded queue holds {}",
        SPEC.queue
    );
    assert_eq!(
        worker.waiting(),
        SPEC.queue as u64,
        "refused jobs do not wait"
    );
    drop(held);
    let mut worker = worker;
    let (replies, service) = worker.finish();
    assert_eq!(worker.waiting(), 0);
    assert_eq!(replies.len(), SPEC.queue + 1, "{replies:?}");
    let service = service.expect("service");
    assert!(service.batches.len() < SPEC.queue, "{:?}", service.batches);
    assert_eq!(worker.handled(), SPEC.queue as u64);
}

//! Row-band parallelism for the per-pixel passes of the depth filter (LSD-SLAM's
//! `IndexThreadReduce` over row ranges, here with `std::thread::scope`).

/// Bands per worker: semi-dense work concentrates in textured rows, so several interleaved
/// bands per worker balance the load better than one contiguous block each.
const BANDS_PER_THREAD: usize = 4;

/// Runs `f(first_row, band)` over contiguous row bands of the row-major `data` (`width`
/// pixels per row) on `threads` workers; returns one result per band, in any order.
pub(crate) fn map_row_bands<T, R, F>(data: &mut [T], width: usize, threads: usize, f: F) -> Vec<R>
where
    T: Send,
    R: Send,
    F: Fn(usize, &mut [T]) -> R + Sync,
{
    let width = width.max(1);
    let height = data.len() / width;
    let threads = threads.clamp(1, height.max(1));
    if threads == 1 {
        return vec![f(0, data)];
    }
    let rows_per_band = height.div_ceil(threads * BANDS_PER_THREAD).max(1);
    let mut work: Vec<Vec<(usize, &mut [T])>> = (0..threads).map(|_| Vec::new()).collect();
    for (i, band) in data.chunks_mut(rows_per_band * width).enumerate() {
        work[i % threads].push((i * rows_per_band, band));
    }
    std::thread::scope(|scope| {
        let f = &f;
        let handles: Vec<_> = work
            .into_iter()
            .map(|bands| {
                scope.spawn(move || {
                    bands
                        .into_iter()
                        .map(|(y0, band)| f(y0, band))
                        .collect::<Vec<R>>()
                })
            })
            .collect();
        handles
            .into_iter()
            .flat_map(|h| {
                h.join()
                    .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
            })
            .collect()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mapping_bands_visit_every_row_once_with_its_index() {
        for threads in [1, 2, 3, 8] {
            let (w, h) = (7, 23);
            let mut data = vec![0usize; w * h];
            let counts = map_row_bands(&mut data, w, threads, |y0, band| {
                for (i, v) in band.iter_mut().enumerate() {
                    *v += y0 * w + i + 1;
                }
                band.len()
            });
            assert_eq!(counts.iter().sum::<usize>(), w * h);
            for (i, v) in data.iter().enumerate() {
                assert_eq!(*v, i + 1, "threads {threads}");
            }
        }
    }
}

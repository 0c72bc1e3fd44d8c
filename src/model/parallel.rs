//! Work spread over threads with results that do not depend on the scheduling: a fit's
//! hypotheses side by side ([`run_parallel`]), and sums and maps over a cloud's points in fixed
//! chunks ([`sum_points`], [`map_points`]).

use rayon::prelude::*;

/// The most threads [`run_parallel`] starts: one for each item up to this many (beyond that each
/// thread takes the next item).
pub(crate) const MAX_THREADS: usize = 8;

/// Runs `job` on every item, each on a thread of its own (up to [`MAX_THREADS`]; beyond that
/// each thread takes the next item), the calling thread among them and the only one that reports
/// `progress`. Results come back in the items' order, so the outcome does not depend on the
/// scheduling.
///
/// A thread an item rather than one a core: the items are a fit's three axis hypotheses or its
/// few carriers or candidates, of about equal length, and on two cores a worker a core runs
/// three of them as two after one (the second core idle for the third), where the operating
/// system's time slicing runs them side by side and finishes in about one and a half.
pub(crate) fn run_parallel<I: Sync, R: Send, P>(
    items: &[I],
    job: impl Fn(&I, &mut dyn FnMut(&P)) -> R + Sync,
    progress: &mut dyn FnMut(&P),
) -> Vec<R> {
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicUsize, Ordering};
    let workers = items.len().min(MAX_THREADS);
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<(usize, R)>> = Mutex::new(Vec::with_capacity(items.len()));
    let work = |progress: &mut dyn FnMut(&P)| {
        loop {
            let i = next.fetch_add(1, Ordering::Relaxed);
            let Some(item) = items.get(i) else { break };
            let r = job(item, progress);
            results
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push((i, r));
        }
    };
    std::thread::scope(|scope| {
        for _ in 1..workers {
            scope.spawn(|| work(&mut |_: &P| {}));
        }
        work(progress);
    });
    let mut results = results.into_inner().unwrap_or_else(|e| e.into_inner());
    results.sort_by_key(|(i, _)| *i);
    results.into_iter().map(|(_, r)| r).collect()
}

/// Clouds at least this large have their per-point sums and maps taken over every core.
pub(crate) const PARALLEL_POINTS: usize = 2048;

/// The points a parallel sum takes as one term: fixed, so that the partial sums, and so the
/// total, come out bit for bit the same whatever the scheduling.
const SUM_CHUNK: usize = 1024;

/// Σ over the indices of `n` points: `add` accumulates point i into a partial sum started by
/// `zero`, and `merge` adds one partial sum into another. Over every core when there are at
/// least [`PARALLEL_POINTS`], in fixed chunks merged in order (deterministic).
pub(crate) fn sum_points<T: Send>(
    n: usize,
    zero: impl Fn() -> T + Sync,
    add: impl Fn(&mut T, usize) + Sync,
    merge: impl Fn(&mut T, &T),
) -> T {
    let range = |range: std::ops::Range<usize>| {
        let mut acc = zero();
        for i in range {
            add(&mut acc, i);
        }
        acc
    };
    if n >= PARALLEL_POINTS {
        let chunk = |c: usize| range(c * SUM_CHUNK..((c + 1) * SUM_CHUNK).min(n));
        let parts: Vec<T> = (0..n.div_ceil(SUM_CHUNK))
            .into_par_iter()
            .map(chunk)
            .collect();
        let mut total = zero();
        for part in &parts {
            merge(&mut total, part);
        }
        total
    } else {
        range(0..n)
    }
}

/// `f` of every index below `n`, in order; over every core when there are at least
/// [`PARALLEL_POINTS`] (each value is computed alone, so the result is the same either way).
pub(crate) fn map_points<T: Send>(n: usize, f: impl Fn(usize) -> T + Sync + Send) -> Vec<T> {
    if n >= PARALLEL_POINTS {
        (0..n).into_par_iter().map(f).collect()
    } else {
        (0..n).map(f).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_come_back_in_order_and_sums_do_not_depend_on_the_chunks() {
        let items: Vec<u64> = (0..20).collect();
        let squares = run_parallel(&items, |i, _: &mut dyn FnMut(&u64)| i * i, &mut |_| {});
        assert_eq!(squares, items.iter().map(|i| i * i).collect::<Vec<_>>());
        for n in [10, PARALLEL_POINTS + 77] {
            let sum = sum_points(n, || 0u64, |s, i| *s += i as u64, |a, b| *a += b);
            assert_eq!(sum, (n as u64 * (n as u64 - 1)) / 2);
            assert_eq!(
                map_points(n, |i| 2 * i),
                (0..n).map(|i| 2 * i).collect::<Vec<_>>()
            );
        }
    }
}

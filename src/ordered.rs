//! Host loops over a mesh's millions of faces or vertices on rayon's
//! threads, with the same bits as one thread's loop.
//!
//! A sum `t_0 + t_1 + ... + t_{n-1}` is kept in its order: its terms are
//! made on rayon's threads, a block at a time (1 MiB of them), and added on the
//! calling thread one after the other, as `Iterator::sum` adds them. The
//! terms (a face's corners gathered, a cross product) are the work; the
//! additions are one each. Dot products of long vectors are made at once,
//! each on one thread, in its own order.

use rayon::prelude::*;

/// Terms made at once before they are added: 1 MiB of `f64`.
const BLOCK: usize = 1 << 17;

/// Below this many terms a loop stays on the calling thread.
const PARALLEL_FROM: usize = 1 << 15;

/// `(0..n).map(term).sum::<f64>()`, to the bit, the terms made on rayon's
/// threads.
pub fn sum_in_order(n: usize, term: impl Fn(usize) -> f64 + Sync) -> f64 {
    if n < PARALLEL_FROM {
        return (0..n).map(term).sum();
    }
    let mut block = vec![0.0; BLOCK];
    // The first block's sum starts where `Iterator::sum` starts; the
    // others go on from it.
    let mut total = None;
    for start in (0..n).step_by(BLOCK) {
        let part = &mut block[..BLOCK.min(n - start)];
        part.par_iter_mut()
            .enumerate()
            .for_each(|(i, t)| *t = term(start + i));
        total = Some(match total {
            None => part.iter().sum::<f64>(),
            Some(acc) => part.iter().fold(acc, |a, t| a + t),
        });
    }
    total.unwrap_or(0.0)
}

/// `out` cleared and refilled with `(0..n).map(term)`, the terms made on
/// rayon's threads where there are many (its storage kept: no fresh pages
/// to fault in on every call).
pub fn fill_at_once<T: Send + Copy + Default>(
    out: &mut Vec<T>,
    n: usize,
    term: impl Fn(usize) -> T + Sync + Send,
) {
    out.clear();
    if n < PARALLEL_FROM {
        out.extend((0..n).map(term));
        return;
    }
    out.resize(n, T::default());
    out.par_iter_mut()
        .enumerate()
        .for_each(|(i, t)| *t = term(i));
}

/// `rayon::join(a, b)`, and the seconds before rayon's threads took the
/// pair up, for the log. From a thread outside rayon's pool the pair waits
/// in the pool's queue of work from outside, which its threads take only
/// once they have no work of their own or to steal (rayon-core's
/// `find_work`): another thread's large parallel step (a fill ordering)
/// holds it back until that step runs out of work to share.
pub fn join_timed<RA: Send, RB: Send>(
    a: impl FnOnce() -> RA + Send,
    b: impl FnOnce() -> RB + Send,
) -> (RA, RB, f64) {
    let queued = std::time::Instant::now();
    let ((waited, ra), rb) = rayon::join(|| (queued.elapsed().as_secs_f64(), a()), b);
    (ra, rb, waited)
}

/// `f()` as one job on rayon's pool (its parallel steps then share the
/// pool's work as its own, not each queued from outside), and the seconds
/// before the pool took it up ([`join_timed`]).
pub fn on_pool_timed<T: Send>(f: impl FnOnce() -> T + Send) -> (T, f64) {
    let (made, (), waited) = join_timed(f, || ());
    (made, waited)
}

/// `f` run in a pool of `threads` of rayon's threads (tests that compare
/// results on several thread counts).
#[cfg(test)]
pub(crate) fn on_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(f)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Terms of mixed signs and sizes, whose sum's bits depend on the order
    /// of its additions: across block boundaries, below the parallel size,
    /// and empty.
    #[test]
    fn the_sum_is_one_threads_to_the_bit() {
        let term = |i: usize| ((i * 7919 % 1009) as f64 - 504.5) * (1.0 + (i % 13) as f64 * 1e-9);
        for n in [
            0,
            1,
            17,
            PARALLEL_FROM - 1,
            PARALLEL_FROM,
            BLOCK + 3,
            3 * BLOCK + 1,
        ] {
            let one: f64 = (0..n).map(term).sum();
            assert_eq!(sum_in_order(n, term).to_bits(), one.to_bits(), "n = {n}");
        }
        // The order matters for these terms: a sum of them reversed differs.
        let n = 3 * BLOCK + 1;
        let forward: f64 = (0..n).map(term).sum();
        let backward: f64 = (0..n).rev().map(term).sum();
        assert_ne!(
            forward.to_bits(),
            backward.to_bits(),
            "terms whose order shows"
        );
    }

    #[test]
    fn filled_terms_keep_their_order() {
        let mut v = vec![7usize; 3];
        for n in [0, 5, PARALLEL_FROM + 7, 2] {
            fill_at_once(&mut v, n, |i| i * i);
            assert_eq!(v, (0..n).map(|i| i * i).collect::<Vec<_>>());
        }
    }
}

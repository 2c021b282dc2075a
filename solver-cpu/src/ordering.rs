//! Nested dissection from the positions of the unknowns: a fill-reducing
//! ordering of a mesh's sparsity pattern (vertices, or face centroids),
//! made on every thread.
//!
//! A set `X` of unknowns is cut by a plane into `L` and `R`: across the one,
//! of the three axes and the cube's four diagonals, whose cut between
//! 64 equal slices of `X`'s extent has the fewest unknowns on its
//! smaller border, each side keeping at least 30 % of `X`. The
//! separator `S` is a minimum vertex cover of the cut's edges (König's
//! theorem, from a maximum matching). The rest of the two sides are ordered
//! first, recursively and at once, and `S` last:
//!
//! ```text
//! order(X) = order(L \ S), order(R \ S), S
//! ```
//!
//! Sets of at most 64 unknowns are ordered by faer's minimum degree,
//! as METIS orders its small parts. With no path from `L \ S` to `R \ S`
//! but through `S`, the two blocks of the factor below them stay zero
//! (George, "Nested dissection of a regular finite element mesh", 1973). On
//! a surface mesh the separators are the curves where planes cut it, of
//! `O(sqrt n)` unknowns, without METIS's one thread (METIS's random numbers
//! are global state, so its calls run one at a time,
//! [`crate::nested_dissection_of_pattern`]); its fill is between METIS's and
//! minimum degree's (BENCHMARKS.md, "Fill orderings from the positions").
//! Each cut is `O(|X|)` work: the whole ordering is `O(n log n)`, its passes
//! and its two halves on rayon's threads. The result depends on the pattern
//! and the positions alone, not on the threads.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::amd;
use faer::sparse::SymbolicSparseColMatRef;
use glam::DVec3;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};

/// Sets this small are the dissection's leaves, ordered by minimum degree.
const LEAF: usize = 64;

/// Each side of a cut holds at least this share of the set.
const BALANCE: f64 = 0.3;

/// Sets from this size on run their passes and their halves on rayon's
/// threads.
const PARALLEL_FROM: usize = 4096;

/// The nested dissection of the symmetric pattern `(col_ptr, row_idx)` (its
/// lower triangle, column by column, as [`crate::SymCsc`]) whose unknown `i`
/// lies at `points[i]`: `forward[new] = old`, as
/// [`crate::FillOrdering::Given`] takes. `None` where the sizes disagree or
/// a position is not finite.
pub fn coordinate_nested_dissection(
    points: &[DVec3],
    col_ptr: &[usize],
    row_idx: &[usize],
) -> Option<Vec<usize>> {
    dissect(points, Adjacency::of_lower(points.len(), col_ptr, row_idx)?)
}

/// As [`coordinate_nested_dissection`], for the pattern whose off-diagonal
/// entries are `pairs` (each once, either way round), e.g. the faces
/// sharing an edge.
pub fn coordinate_nested_dissection_of_pairs(
    points: &[DVec3],
    pairs: &[[u32; 2]],
) -> Option<Vec<usize>> {
    let edges = pairs.iter().map(|p| (p[0] as usize, p[1] as usize));
    dissect(points, Adjacency::of_edges(points.len(), edges)?)
}

fn dissect(points: &[DVec3], graph: Adjacency) -> Option<Vec<usize>> {
    let n = points.len();
    if !points.iter().all(|p| p.is_finite()) {
        return None;
    }
    let points: Vec<[f64; 3]> = points.iter().map(|p| p.to_array()).collect();
    let labels: Vec<AtomicU32> = (0..n).map(|_| AtomicU32::new(0)).collect();
    let bucket: Vec<AtomicU64> = (0..n).map(|_| AtomicU64::new(0)).collect();
    let dissection = Dissection {
        points: &points,
        graph: &graph,
        labels: &labels,
        next_label: AtomicU32::new(1),
        bucket: &bucket,
    };
    let all: Vec<u32> = (0..n as u32).collect();
    let extent = per_chunk(&all, |part| {
        Extent::of(part.iter().map(|&v| points[v as usize]))
    })
    .into_iter()
    .fold(Extent::empty(), Extent::union);
    let mut forward = vec![0u32; n];
    dissection.order(all, extent, 0, 0, &mut forward);
    Some(forward.into_iter().map(|v| v as usize).collect())
}

/// Both triangles of a symmetric pattern, diagonal left out: `adj[xadj[v]..
/// xadj[v + 1]]` are `v`'s neighbours, in the order of the entries they come
/// from (as METIS takes a graph, [`crate::nested_dissection_of_pattern`]).
pub(crate) struct Adjacency {
    pub(crate) xadj: Vec<usize>,
    pub(crate) adj: Vec<u32>,
}

impl Adjacency {
    /// From the lower-triangular pattern `(col_ptr, row_idx)` of an `n x n`
    /// symmetric matrix, column by column. `None` where the sizes disagree.
    pub(crate) fn of_lower(n: usize, col_ptr: &[usize], row_idx: &[usize]) -> Option<Adjacency> {
        if col_ptr.len() != n + 1
            || col_ptr.last() != Some(&row_idx.len())
            || col_ptr.windows(2).any(|w| w[0] > w[1])
        {
            return None;
        }
        let edges = (0..n).flat_map(|c| {
            row_idx[col_ptr[c]..col_ptr[c + 1]]
                .iter()
                .map(move |&r| (r, c))
        });
        Adjacency::of_edges(n, edges)
    }

    /// From the entries `(r, c)` of a symmetric pattern, each pair once;
    /// the diagonal's are left out. `None` where an index is out of range,
    /// or `n` or the entries too many for 32-bit indices (METIS's).
    fn of_edges(
        n: usize,
        edges: impl Iterator<Item = (usize, usize)> + Clone,
    ) -> Option<Adjacency> {
        if n >= i32::MAX as usize {
            return None;
        }
        let mut xadj = vec![0usize; n + 1];
        for (r, c) in edges.clone() {
            if r >= n || c >= n {
                return None;
            }
            if r != c {
                xadj[r + 1] += 1;
                xadj[c + 1] += 1;
            }
        }
        for i in 0..n {
            xadj[i + 1] += xadj[i];
        }
        if xadj[n] > i32::MAX as usize {
            return None;
        }
        let mut fill = xadj.clone();
        let mut adj = vec![0u32; xadj[n]];
        for (r, c) in edges {
            if r != c {
                adj[fill[r]] = c as u32;
                fill[r] += 1;
                adj[fill[c]] = r as u32;
                fill[c] += 1;
            }
        }
        Some(Adjacency { xadj, adj })
    }

    fn neighbours(&self, v: u32) -> &[u32] {
        &self.adj[self.xadj[v as usize]..self.xadj[v as usize + 1]]
    }
}

/// Cuts tried along each direction: between this many equal slices.
const BUCKETS: usize = 64;

/// Unknowns a thread takes at once in a set's passes.
const CHUNK: usize = 8192;

/// `pass` of each chunk of [`CHUNK`] unknowns of `set`, in order, on
/// rayon's threads where the set has [`PARALLEL_FROM`] unknowns or more;
/// else of the whole set, as one chunk.
fn per_chunk<R: Send>(set: &[u32], pass: impl Fn(&[u32]) -> R + Sync + Send) -> Vec<R> {
    if set.len() >= PARALLEL_FROM {
        set.par_chunks(CHUNK).map(pass).collect()
    } else {
        vec![pass(set)]
    }
}

/// The chunks' parts of a set, concatenated in order (one part: itself).
fn joined(mut parts: Vec<Vec<u32>>) -> Vec<u32> {
    if parts.len() == 1 {
        parts.pop().unwrap()
    } else {
        parts.concat()
    }
}

/// Directions the sets are cut across: the axes and the cube's diagonals
/// (`DIRECTIONS`, in the order of [`projections`]).
const DIRS: usize = 7;
#[cfg(test)]
const DIRECTIONS: [[f64; 3]; DIRS] = [
    [1.0, 0.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, 0.0, 1.0],
    [1.0, 1.0, 1.0],
    [1.0, 1.0, -1.0],
    [1.0, -1.0, 1.0],
    [-1.0, 1.0, 1.0],
];

/// A set's counts per direction and bucket: its unknowns, and the
/// changes, cut by cut, of its left and right borders.
struct Tally {
    count: [[i64; BUCKETS + 1]; DIRS],
    left: [[i64; BUCKETS + 1]; DIRS],
    right: [[i64; BUCKETS + 1]; DIRS],
}

impl Default for Tally {
    fn default() -> Tally {
        Tally {
            count: [[0; BUCKETS + 1]; DIRS],
            left: [[0; BUCKETS + 1]; DIRS],
            right: [[0; BUCKETS + 1]; DIRS],
        }
    }
}

impl Tally {
    fn add(mut self, other: Tally) -> Tally {
        for d in 0..DIRS {
            for b in 0..=BUCKETS {
                self.count[d][b] += other.count[d][b];
                self.left[d][b] += other.left[d][b];
                self.right[d][b] += other.right[d][b];
            }
        }
        self
    }
}

/// Each direction's slices of a set's extent: the bucket of `p` along
/// direction `d` is `(p . d - lo[d]) * per[d]`, in `0..BUCKETS`.
struct Buckets {
    lo: [f64; DIRS],
    per: [f64; DIRS],
}

/// The least and most projections of some points on each direction.
struct Extent {
    lo: [f64; DIRS],
    hi: [f64; DIRS],
}

impl Extent {
    /// The extent of `points`.
    fn of(points: impl Iterator<Item = [f64; 3]>) -> Extent {
        let mut e = Extent::empty();
        for p in points {
            for (d, x) in projections(p).into_iter().enumerate() {
                e.lo[d] = e.lo[d].min(x);
                e.hi[d] = e.hi[d].max(x);
            }
        }
        e
    }

    fn empty() -> Extent {
        Extent {
            lo: [f64::INFINITY; DIRS],
            hi: [f64::NEG_INFINITY; DIRS],
        }
    }

    fn union(mut self, other: Extent) -> Extent {
        for d in 0..DIRS {
            self.lo[d] = self.lo[d].min(other.lo[d]);
            self.hi[d] = self.hi[d].max(other.hi[d]);
        }
        self
    }

    /// [`BUCKETS`] equal slices of the extent along each direction.
    fn buckets(self) -> Buckets {
        let Extent { lo, hi } = self;
        let mut per = [0.0; DIRS];
        for d in 0..DIRS {
            let extent = hi[d] - lo[d];
            per[d] = if extent > 0.0 {
                BUCKETS as f64 / extent
            } else {
                0.0
            };
        }
        Buckets { lo, per }
    }
}

impl Buckets {
    /// The bucket of a point whose projection on direction `d` is `x`.
    fn of(&self, x: f64, d: usize) -> usize {
        let b = (x - self.lo[d]) * self.per[d];
        (b as usize).min(BUCKETS - 1)
    }
}

/// 1 in each of the bytes that hold a direction's bucket.
const LANES: u64 = 0x0001_0101_0101_0101;

/// Per byte, whether `a`'s is at least `b`'s (0xff or 0), for bytes below 128.
fn bytewise_at_least(a: u64, b: u64) -> u64 {
    let high = LANES * 0x80;
    ((((a | high) - b) & high) >> 7) * 0xff
}

fn bytewise_max(a: u64, b: u64) -> u64 {
    let m = bytewise_at_least(a, b);
    (a & m) | (b & !m)
}

fn bytewise_min(a: u64, b: u64) -> u64 {
    let m = bytewise_at_least(a, b);
    (b & m) | (a & !m)
}

/// `p`'s projections on the directions (`DIRECTIONS`), `p . d` summed as
/// `(p0 d0 + p1 d1) + p2 d2`: a product with 1, -1 or 0 is exact, so these
/// sums and differences are the same values (a zero's sign aside, which no
/// bucket sees), with no products.
fn projections(p: [f64; 3]) -> [f64; DIRS] {
    let [x, y, z] = p;
    [x, y, z, (x + y) + z, (x + y) - z, (x - y) + z, (y - x) + z]
}

/// The state the recursion shares. Each set being split marks its
/// unknowns with labels of its own, fresh from `next_label`; a label is
/// never given twice, so a set's test "is this neighbour in my half" reads
/// true for its own unknowns only, whatever the sets being split at the
/// same time on other threads write.
struct Dissection<'a> {
    points: &'a [[f64; 3]],
    graph: &'a Adjacency,
    labels: &'a [AtomicU32],
    next_label: AtomicU32,
    /// Each unknown's bucket along each direction, 8 bits each, in its
    /// set's current cut.
    bucket: &'a [AtomicU64],
}

impl Dissection<'_> {
    fn fresh_label(&self) -> u32 {
        self.next_label.fetch_add(1, Ordering::Relaxed)
    }

    fn label(&self, v: u32) -> u32 {
        self.labels[v as usize].load(Ordering::Relaxed)
    }

    fn mark(&self, set: &[u32], label: u32) {
        per_chunk(set, |part| {
            for &v in part {
                self.labels[v as usize].store(label, Ordering::Relaxed);
            }
        });
    }

    /// Writes the order of `set` (whose unknowns are labelled `label`, and
    /// whose positions span `extent`) into `out` (as long as `set`).
    fn order(&self, set: Vec<u32>, extent: Extent, label: u32, depth: usize, out: &mut [u32]) {
        if set.len() <= LEAF || depth > 64 {
            self.order_leaf(&set, out);
            return;
        }
        let (d, cut) = self.best_cut(&set, extent.buckets(), label);
        // The bucket `best_cut` stored, not made again from the position.
        let on_left = |v: u32| {
            ((self.bucket[v as usize].load(Ordering::Relaxed) >> (8 * d)) & 0xff) < cut as u64
        };
        // A large set's passes on rayon's threads (the halves keep the
        // set's order either way): the first cuts' sets are the largest,
        // and few of them run at once.
        let (left, right): (Vec<Vec<u32>>, Vec<Vec<u32>>) =
            per_chunk(&set, |part| part.iter().partition(|&&v| on_left(v)))
                .into_iter()
                .unzip();
        let (mut left, mut right) = (joined(left), joined(right));
        if left.is_empty() || right.is_empty() {
            // Every position alike along every direction: no cut to make.
            self.order_leaf(&set, out);
            return;
        }
        drop(set);
        let (l, r) = (self.fresh_label(), self.fresh_label());
        self.mark(&left, l);
        self.mark(&right, r);
        let separator = self.cover(&left, r);
        let sep = self.fresh_label();
        // The separator's unknowns leave both halves' labels.
        self.mark(&separator, sep);
        // Each half's extent made in the same pass, for its own cut (none
        // for a leaf, which is not cut).
        let mut extents = [Extent::empty(), Extent::empty()];
        for (half, extent) in [&mut left, &mut right].into_iter().zip(&mut extents) {
            let cut_again = half.len() > LEAF;
            let kept = |part: &[u32]| -> (Vec<u32>, Extent) {
                let kept: Vec<u32> = part
                    .iter()
                    .copied()
                    .filter(|&v| self.label(v) != sep)
                    .collect();
                let extent = if cut_again {
                    Extent::of(kept.iter().map(|&v| self.points[v as usize]))
                } else {
                    Extent::empty()
                };
                (kept, extent)
            };
            let (parts, extents): (Vec<Vec<u32>>, Vec<Extent>) =
                per_chunk(half, kept).into_iter().unzip();
            *half = joined(parts);
            *extent = extents.into_iter().fold(Extent::empty(), Extent::union);
        }
        let [left_extent, right_extent] = extents;
        let (out_left, rest) = out.split_at_mut(left.len());
        let (out_right, out_sep) = rest.split_at_mut(right.len());
        out_sep.copy_from_slice(&separator);
        if left.len() + right.len() >= PARALLEL_FROM {
            rayon::join(
                || self.order(left, left_extent, l, depth + 1, out_left),
                || self.order(right, right_extent, r, depth + 1, out_right),
            );
        } else {
            self.order(left, left_extent, l, depth + 1, out_left);
            self.order(right, right_extent, r, depth + 1, out_right);
        }
    }

    /// Where to cut `set` (labelled `label`): the direction and the
    /// bucket boundary (buckets below `cut` on the left) whose cut has the
    /// fewest unknowns on its smaller border, of the cuts between
    /// [`BUCKETS`] equal slices of the set's extent along each direction
    /// (`buckets`) that leave each side at least [`BALANCE`] of the set. An
    /// unknown in bucket `b` whose neighbours in the set reach buckets
    /// `lo..=hi` is on the left border of the cuts `b < t <= hi` and on the
    /// right border of `lo < t <= b`.
    fn best_cut(&self, set: &[u32], buckets: Buckets, label: u32) -> (usize, usize) {
        let m = set.len();
        let pack = |v: u32| -> u64 {
            let x = projections(self.points[v as usize]);
            (0..DIRS).fold(0u64, |packed, d| {
                packed | (buckets.of(x[d], d) as u64) << (8 * d)
            })
        };
        per_chunk(set, |part| {
            for &v in part {
                self.bucket[v as usize].store(pack(v), Ordering::Relaxed);
            }
        });
        let tally = |part: &[u32]| -> Tally {
            let mut t = Tally::default();
            for &v in part {
                let own = self.bucket[v as usize].load(Ordering::Relaxed);
                // Bytewise least and most of its own and its neighbours'
                // buckets, all directions at once (buckets are below 128).
                let (mut lo, mut hi) = (own, own);
                for &u in self.graph.neighbours(v) {
                    if self.label(u) == label {
                        let theirs = self.bucket[u as usize].load(Ordering::Relaxed);
                        lo = bytewise_min(lo, theirs);
                        hi = bytewise_max(hi, theirs);
                    }
                }
                // With no neighbour beyond its own bucket (`hi == b` or
                // `lo == b`) each pair of changes below cancels: no branch.
                for d in 0..DIRS {
                    let b = (own >> (8 * d)) as u8 as usize;
                    let (lo, hi) = (
                        (lo >> (8 * d)) as u8 as usize,
                        (hi >> (8 * d)) as u8 as usize,
                    );
                    t.count[d][b] += 1;
                    t.left[d][b + 1] += 1;
                    t.left[d][hi + 1] -= 1;
                    t.right[d][lo + 1] += 1;
                    t.right[d][b + 1] -= 1;
                }
            }
            t
        };
        let t = per_chunk(set, tally)
            .into_iter()
            .fold(Tally::default(), Tally::add);
        let least = ((m as f64) * BALANCE) as i64;
        // (border, imbalance, direction, cut)
        let mut best: Option<(i64, i64, usize, usize)> = None;
        for d in 0..DIRS {
            let (mut on_left, mut bl, mut br) = (0i64, 0i64, 0i64);
            for cut in 1..BUCKETS {
                on_left += t.count[d][cut - 1];
                bl += t.left[d][cut];
                br += t.right[d][cut];
                if on_left < least || m as i64 - on_left < least {
                    continue;
                }
                let key = (bl.min(br), (2 * on_left - m as i64).abs(), d, cut);
                if best.is_none_or(|b| (key.0, key.1) < (b.0, b.1)) {
                    best = Some(key);
                }
            }
        }
        match best {
            Some((_, _, d, cut)) => (d, cut),
            // No cut balanced enough (many equal positions): the middle.
            None => (0, BUCKETS / 2),
        }
    }

    /// The smallest set of unknowns touching every edge between the halves
    /// `left` and the one labelled `r`: a minimum vertex cover of the cut's
    /// bipartite graph (König's theorem, from a maximum matching).
    fn cover(&self, left: &[u32], r: u32) -> Vec<u32> {
        use std::collections::HashMap;
        // The cut's edges, from the left's border to the right's.
        let mut right_index: HashMap<u32, usize> = HashMap::new();
        let mut right_border: Vec<u32> = Vec::new();
        let mut left_border: Vec<u32> = Vec::new();
        let mut edges_ptr = vec![0usize];
        let mut edges: Vec<usize> = Vec::new();
        for &v in left {
            let before = edges.len();
            for &u in self.graph.neighbours(v) {
                if self.label(u) == r {
                    let next = right_border.len();
                    let j = *right_index.entry(u).or_insert(next);
                    if j == next {
                        right_border.push(u);
                    }
                    edges.push(j);
                }
            }
            if edges.len() > before {
                left_border.push(v);
                edges_ptr.push(edges.len());
            }
        }
        let (nl, nr) = (left_border.len(), right_border.len());
        const FREE: usize = usize::MAX;
        let mut match_left = vec![FREE; nl];
        let mut match_right = vec![FREE; nr];
        // Greedy start, then augmenting paths (depth first, iterative).
        for i in 0..nl {
            for &j in &edges[edges_ptr[i]..edges_ptr[i + 1]] {
                if match_right[j] == FREE {
                    match_right[j] = i;
                    match_left[i] = j;
                    break;
                }
            }
        }
        let mut seen = vec![usize::MAX; nr];
        let mut stack: Vec<(usize, usize)> = Vec::new();
        for start in 0..nl {
            if match_left[start] != FREE {
                continue;
            }
            stack.clear();
            stack.push((start, edges_ptr[start]));
            let mut found = None;
            while let Some(&mut (i, ref mut e)) = stack.last_mut() {
                if *e == edges_ptr[i + 1] {
                    stack.pop();
                    continue;
                }
                let j = edges[*e];
                *e += 1;
                if seen[j] == start {
                    continue;
                }
                seen[j] = start;
                if match_right[j] == FREE {
                    found = Some(j);
                    break;
                }
                let next = match_right[j];
                stack.push((next, edges_ptr[next]));
            }
            if let Some(mut j) = found {
                // Flip the path: each left unknown on the stack takes the
                // right one it reached.
                while let Some((i, _)) = stack.pop() {
                    let was = match_left[i];
                    match_left[i] = j;
                    match_right[j] = i;
                    j = was;
                }
            }
        }
        // König: Z, what alternating paths reach from the free left
        // unknowns; the cover is the left border outside Z and the right
        // border inside it.
        let mut in_z_left = vec![false; nl];
        let mut in_z_right = vec![false; nr];
        let mut queue: Vec<usize> = (0..nl).filter(|&i| match_left[i] == FREE).collect();
        for &i in &queue {
            in_z_left[i] = true;
        }
        while let Some(i) = queue.pop() {
            for &j in &edges[edges_ptr[i]..edges_ptr[i + 1]] {
                if !in_z_right[j] {
                    in_z_right[j] = true;
                    let k = match_right[j];
                    if k != FREE && !in_z_left[k] {
                        in_z_left[k] = true;
                        queue.push(k);
                    }
                }
            }
        }
        let mut cover: Vec<u32> = (0..nl)
            .filter(|&i| !in_z_left[i])
            .map(|i| left_border[i])
            .collect();
        cover.extend((0..nr).filter(|&j| in_z_right[j]).map(|j| right_border[j]));
        cover
    }

    /// A leaf's minimum-degree order (faer's AMD on the graph `set` induces),
    /// as METIS orders its small parts; `set` as it is where AMD fails.
    fn order_leaf(&self, set: &[u32], out: &mut [u32]) {
        let m = set.len();
        let mut local: Vec<(u32, usize)> = set.iter().enumerate().map(|(i, &v)| (v, i)).collect();
        local.sort_unstable();
        let mut col_ptr = Vec::with_capacity(m + 1);
        let mut row_idx = Vec::new();
        col_ptr.push(0usize);
        for (i, &v) in set.iter().enumerate() {
            for &u in self.graph.neighbours(v) {
                if let Ok(k) = local.binary_search_by_key(&u, |e| e.0) {
                    if local[k].1 != i {
                        row_idx.push(local[k].1);
                    }
                }
            }
            col_ptr.push(row_idx.len());
        }
        let mut perm = vec![0usize; m];
        let mut perm_inv = vec![0usize; m];
        let mut mem = MemBuffer::new(amd::order_maybe_unsorted_scratch::<usize>(m, row_idx.len()));
        let ordered = amd::order_maybe_unsorted(
            &mut perm,
            &mut perm_inv,
            SymbolicSparseColMatRef::new_unsorted_checked(m, m, &col_ptr, None, &row_idx),
            amd::Control::default(),
            MemStack::new(&mut mem),
        );
        match ordered {
            Ok(_) => {
                for (o, &p) in out.iter_mut().zip(&perm) {
                    *o = set[p];
                }
            }
            Err(_) => out.copy_from_slice(set),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{CholeskySolver, FillOrdering, SpdSolver, SymCsc};

    /// A `w x h` grid of vertices wrapped round a cylinder (around it `w`,
    /// along it `h`), triangulated: each vertex paired with the next one
    /// around, the one above and the one above and next. Its positions and
    /// pairs.
    fn cylinder(w: usize, h: usize) -> (Vec<DVec3>, Vec<[u32; 2]>) {
        let at = |i: usize, j: usize| (j * w + i % w) as u32;
        let mut points = Vec::with_capacity(w * h);
        let mut pairs = Vec::new();
        for j in 0..h {
            for i in 0..w {
                let angle = std::f64::consts::TAU * i as f64 / w as f64;
                points.push(DVec3::new(angle.cos(), angle.sin(), 0.05 * j as f64));
                pairs.push([at(i, j), at(i + 1, j)]);
                if j + 1 < h {
                    pairs.push([at(i, j), at(i, j + 1)]);
                    pairs.push([at(i, j), at(i + 1, j + 1)]);
                }
            }
        }
        (points, pairs)
    }

    fn pattern(n: usize, pairs: &[[u32; 2]]) -> SymCsc {
        SymCsc::from_pattern(n, pairs.iter().map(|p| (p[0] as usize, p[1] as usize)))
    }

    /// Values of `pattern`'s Cholesky factor in `ordering`.
    fn factor_values(pattern: &SymCsc, ordering: FillOrdering) -> usize {
        let mut c = CholeskySolver::new();
        c.set_fill_ordering(ordering);
        c.analyse(pattern).unwrap();
        c.factor_nnz()
    }

    fn is_permutation(forward: &[usize]) -> bool {
        let mut sorted = forward.to_vec();
        sorted.sort_unstable();
        sorted.iter().enumerate().all(|(i, &v)| i == v)
    }

    #[test]
    fn projections_are_the_dot_products_with_the_directions() {
        let values = [0.0, -0.0, 1.0, -2.5, 0.1, 1e-300, -3e17, 7.25e-3];
        for &x in &values {
            for &y in &values {
                for &z in &values {
                    let p = [x, y, z];
                    for (d, got) in projections(p).into_iter().enumerate() {
                        let e = DIRECTIONS[d];
                        let dot = p[0] * e[0] + p[1] * e[1] + p[2] * e[2];
                        assert_eq!(got, dot, "{p:?} on {e:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn the_dissection_is_a_permutation_with_less_fill_than_minimum_degree() {
        let (points, pairs) = cylinder(120, 200);
        let a = pattern(points.len(), &pairs);
        let forward = coordinate_nested_dissection(&points, &a.col_ptr, &a.row_idx).unwrap();
        assert!(is_permutation(&forward));
        let natural = factor_values(&a, FillOrdering::Given((0..a.n).collect()));
        let amd = factor_values(&a, FillOrdering::Amd);
        let dissected = factor_values(&a, FillOrdering::Given(forward.into()));
        assert!(
            dissected < natural / 2 && dissected < amd,
            "factor values: dissected {dissected}, natural {natural}, minimum degree {amd}"
        );
    }

    #[test]
    fn the_faces_dissection_is_a_permutation_with_less_fill_than_the_natural_order() {
        // The dual graph of the cylinder's triangles, at their centroids.
        let (w, h) = (150, 160);
        let (points, _) = cylinder(w, h);
        let at = |i: usize, j: usize| j * w + i % w;
        let (mut centroids, mut faces) = (Vec::new(), Vec::new());
        for j in 0..h - 1 {
            for i in 0..w {
                faces.push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
                faces.push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
            }
        }
        for f in &faces {
            centroids.push(f.iter().map(|&v| points[v]).sum::<DVec3>() / 3.0);
        }
        let mut by_edge = std::collections::HashMap::new();
        let mut pairs = Vec::new();
        for (fi, f) in faces.iter().enumerate() {
            for e in 0..3 {
                let (a, b) = (f[e].min(f[(e + 1) % 3]), f[e].max(f[(e + 1) % 3]));
                if let Some(other) = by_edge.insert((a, b), fi) {
                    pairs.push([other as u32, fi as u32]);
                }
            }
        }
        let forward = coordinate_nested_dissection_of_pairs(&centroids, &pairs).unwrap();
        assert!(is_permutation(&forward));
        let a = pattern(faces.len(), &pairs);
        let natural = factor_values(&a, FillOrdering::Given((0..a.n).collect()));
        let dissected = factor_values(&a, FillOrdering::Given(forward.into()));
        assert!(
            dissected < natural / 2,
            "factor values: dissected {dissected}, natural {natural}"
        );
    }

    #[test]
    fn the_dissection_is_the_same_on_any_number_of_threads() {
        let (points, pairs) = cylinder(100, 150);
        let a = pattern(points.len(), &pairs);
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| coordinate_nested_dissection(&points, &a.col_ptr, &a.row_idx))
        };
        let one = on(1).unwrap();
        assert_eq!(one, on(4).unwrap());
        assert_eq!(one, on(3).unwrap());
    }

    #[test]
    fn a_bad_pattern_or_position_gives_no_ordering() {
        let (mut points, pairs) = cylinder(10, 10);
        let a = pattern(points.len(), &pairs);
        assert!(coordinate_nested_dissection(&points[1..], &a.col_ptr, &a.row_idx).is_none());
        let mut backwards = a.col_ptr.clone();
        backwards.swap(3, 4);
        assert!(coordinate_nested_dissection(&points, &backwards, &a.row_idx).is_none());
        assert!(coordinate_nested_dissection_of_pairs(&points, &[[0, 100]]).is_none());
        points[7].y = f64::NAN;
        assert!(coordinate_nested_dissection(&points, &a.col_ptr, &a.row_idx).is_none());
        assert!(coordinate_nested_dissection_of_pairs(&points, &pairs).is_none());
    }
}

//! A whole object's parts assembled from small patches by description length: the patches of
//! [`super::patches`] merged two at a time, the cheapest merge first, while a merge lowers the
//! cost of describing the points ([`super::split`]'s module docs give the cost).
//!
//! Each piece is a pure superquadric fitted to its points ([`fit_lean`]). Merging two touching
//! pieces a and b into one piece m saves a part's price, and changes what the points and the
//! surfaces cost. ΔL is the whole object's cost, restricted to a and b, the pieces that touch
//! them, and all their points: with m in place of a and b, less the price of a part. The union
//! is what is measured, as for the whole object: a point inside another piece costs at least
//! its depth there, and a surface hidden inside another piece costs nothing.
//!
//! Merges are tried in the order of how much they raise the points' cost (two patches of one
//! smooth piece of surface first, two pieces across a crease last), and each is taken when
//! ΔL < 0. A superquadric is convex, so a piece that reaches across a concave crease (a limb
//! into a body) leaves points off its surface, and the merge does not pay.
//!
//! A merge's fit is made once and kept while its two pieces stand; what it saves is measured
//! again, without a fit, whenever a piece it involves has changed since (lazy evaluation: a
//! merge is taken only on a measure that is current).

use super::split::{Data, Part, Scale, cost_of};
use crate::model::fit::{FitError, FitOptions, Initialization, MIN_POINTS, fit_lean};
use crate::model::parallel::run_parallel;
use glam::DVec3;
use std::collections::{BTreeMap, BTreeSet};

/// The tessellation a piece's surface is measured on: k = 12, 146 nodes.
pub(super) const PIECE_K: usize = 12;

/// Stale merges fitted or measured at once when the best is stale: the best and the next ones
/// side by side.
const REFRESH_BATCH: usize = 4;

/// A merge of two pieces: the merged piece (`None` until fitted), the (raise, ΔL) it was last
/// measured at, and the step of the merging it was measured at (`None`: not since its fit or
/// its pieces changed).
struct Candidate {
    piece: Option<Part>,
    estimate: (f64, f64),
    measured: Option<usize>,
}

/// What the pieces are fitted and measured against.
pub(super) struct Assembly<'a> {
    points: &'a [DVec3],
    data: &'a Data,
    scale: &'a Scale,
    opts: &'a FitOptions,
}

/// The pieces while they are merged: each piece (`None` once merged into another), the pieces
/// it touches, and the step at which it or its neighbours last changed.
struct Pieces {
    piece: Vec<Option<Part>>,
    links: Vec<BTreeMap<usize, usize>>,
    changed: Vec<usize>,
}

impl Pieces {
    /// Pieces `a` and `b` and those that touch them: what a merge of the two is measured on.
    fn around(&self, a: usize, b: usize) -> Vec<usize> {
        let mut set: BTreeSet<usize> = [a, b].into();
        set.extend(self.links[a].keys().chain(self.links[b].keys()));
        set.into_iter()
            .filter(|&c| self.piece[c].is_some())
            .collect()
    }

    /// Moves `from`'s links to `into` (edge counts added), and drops `from`'s.
    fn join_links(&mut self, from: usize, into: usize) {
        let moved = std::mem::take(&mut self.links[from]);
        for (c, e) in moved {
            self.links[c].remove(&from);
            if c != into {
                *self.links[into].entry(c).or_insert(0) += e;
                *self.links[c].entry(into).or_insert(0) += e;
            }
        }
        self.links[into].remove(&from);
    }
}

impl<'a> Assembly<'a> {
    /// The assembly of `points` (the cloud the cost is measured on) with the pure options
    /// `opts`.
    pub fn new(
        points: &'a [DVec3],
        data: &'a Data,
        scale: &'a Scale,
        opts: &'a FitOptions,
    ) -> Self {
        Self {
            points,
            data,
            scale,
            opts,
        }
    }

    /// The piece of `members` (at least [`MIN_POINTS`]), its fit started from `init`.
    fn piece(&self, members: Vec<usize>, init: Initialization) -> Result<Part, FitError> {
        let own: Vec<DVec3> = members.iter().map(|&i| self.points[i]).collect();
        let opts = FitOptions {
            global_only: true,
            init,
            k: PIECE_K,
            ..*self.opts
        };
        let pose = fit_lean(&own, &opts)?;
        Ok(Part::new(self.points, self.data, pose, members))
    }

    /// (raise, ΔL) of merging `a` and `b` into `merged` (module docs), on the pieces as they are.
    fn measure(&self, pieces: &Pieces, a: usize, b: usize, merged: &Part) -> (f64, f64) {
        let around = pieces.around(a, b);
        let mut which: Vec<usize> = around
            .iter()
            .filter_map(|&c| pieces.piece[c].as_ref())
            .flat_map(|p| p.members.iter().copied())
            .collect();
        which.sort_unstable();
        let before: Vec<&Part> = around
            .iter()
            .filter_map(|&c| pieces.piece[c].as_ref())
            .collect();
        let after: Vec<&Part> = around
            .iter()
            .filter(|&&c| c != a && c != b)
            .filter_map(|&c| pieces.piece[c].as_ref())
            .chain(std::iter::once(merged))
            .collect();
        let (p0, s0) = cost_of(&before, Some(&which), self.data, self.scale);
        let (p1, s1) = cost_of(&after, Some(&which), self.data, self.scale);
        (p1 - p0, p1 + s1 - p0 - s0 - self.scale.part)
    }

    /// The pieces `patch` (each point's patch, `count` of them, touching as `adjacent` says)
    /// merged while merging lowers the cost (module docs), then, while there are more than
    /// `cap`, the merges that raise it least. Patches under [`MIN_POINTS`] points are first
    /// joined to the neighbour they share most edges with.
    pub fn merge(
        &self,
        patch: &[usize],
        adjacent: &[Vec<(usize, usize)>],
        cap: usize,
    ) -> Result<Vec<Part>, FitError> {
        let count = adjacent.len();
        let mut members: Vec<Vec<usize>> = vec![Vec::new(); count];
        for (i, &p) in patch.iter().enumerate() {
            members[p].push(i);
        }
        let mut pieces = Pieces {
            piece: (0..count).map(|_| None).collect(),
            links: adjacent
                .iter()
                .map(|a| a.iter().copied().collect())
                .collect(),
            changed: vec![0; count],
        };
        let mut alive: Vec<bool> = members.iter().map(|m| !m.is_empty()).collect();
        // Too small to fit: into the best-joined neighbour.
        while let Some(k) = (0..count).find(|&k| alive[k] && members[k].len() < MIN_POINTS) {
            alive[k] = false;
            let best = pieces.links[k]
                .iter()
                .filter(|(j, _)| alive[**j])
                .max_by_key(|(j, e)| (**e, std::cmp::Reverse(**j)))
                .map(|(j, _)| *j);
            if let Some(j) = best {
                let moved = std::mem::take(&mut members[k]);
                members[j].extend(moved);
                pieces.join_links(k, j);
            }
        }
        let ids: Vec<usize> = (0..count).filter(|&k| alive[k]).collect();
        let fitted = run_parallel(
            &ids,
            |&k, _| self.piece(members[k].clone(), Initialization::Moments),
            &mut |_: &()| {},
        );
        for (&k, p) in ids.iter().zip(fitted) {
            pieces.piece[k] = Some(p?);
        }
        let mut candidates: BTreeMap<(usize, usize), Candidate> = ids
            .iter()
            .flat_map(|&a| {
                pieces.links[a]
                    .keys()
                    .filter(move |&&b| b > a)
                    .map(move |&b| (a, b))
            })
            .filter(|&(_, b)| alive[b])
            .map(|pair| {
                let c = Candidate {
                    piece: None,
                    estimate: (f64::NEG_INFINITY, f64::NEG_INFINITY),
                    measured: None,
                };
                (pair, c)
            })
            .collect();
        let mut live = ids.len();
        let mut step = 0;
        loop {
            let over = live > cap;
            let key = |e: &(f64, f64)| if over { e.1 } else { e.0 };
            let mut order: Vec<((usize, usize), bool)> = candidates
                .iter()
                .filter(|(_, c)| over || c.estimate.1 < 0.0)
                .map(|(k, c)| (*k, current(c, &pieces, *k)))
                .collect();
            order.sort_by(|x, y| {
                key(&candidates[&x.0].estimate)
                    .total_cmp(&key(&candidates[&y.0].estimate))
                    .then(x.0.cmp(&y.0))
            });
            let refresh: Vec<(usize, usize)> = match order.first() {
                Some(&(best, true)) => {
                    self.take(best, &mut candidates, &mut pieces, step);
                    step += 1;
                    live -= 1;
                    continue;
                }
                // The best is stale: measure it, with the next few stale ones.
                Some(_) => order
                    .iter()
                    .filter(|o| !o.1)
                    .take(REFRESH_BATCH)
                    .map(|o| o.0)
                    .collect(),
                // No merge looks worth it on its last measure: measure every stale one, in
                // case the pieces' growth changed that.
                None => candidates
                    .iter()
                    .filter(|(k, c)| !current(c, &pieces, **k))
                    .map(|(k, _)| *k)
                    .collect(),
            };
            if refresh.is_empty() {
                break;
            }
            self.refresh(&refresh, &mut candidates, &pieces, step)?;
        }
        Ok(pieces.piece.into_iter().flatten().collect())
    }

    /// Merges the pair `(a, b)` of `candidates` into `a` at step `step`: the pairs of a or b
    /// with a third piece become pairs of the merged piece, stale, estimated by the cheaper of
    /// the two until measured.
    fn take(
        &self,
        (a, b): (usize, usize),
        candidates: &mut BTreeMap<(usize, usize), Candidate>,
        pieces: &mut Pieces,
        step: usize,
    ) {
        let merged = candidates.remove(&(a, b)).and_then(|c| c.piece);
        let mut estimates: BTreeMap<usize, (f64, f64)> = BTreeMap::new();
        let old: Vec<((usize, usize), Candidate)> = candidates
            .extract_if(.., |&(x, y), _| x == a || y == a || x == b || y == b)
            .collect();
        for ((x, y), c) in old {
            let other = if x == a || x == b { y } else { x };
            let e = estimates.entry(other).or_insert(c.estimate);
            if c.estimate.0 < e.0 {
                *e = c.estimate;
            }
        }
        let touched: Vec<usize> = pieces.around(a, b);
        pieces.piece[a] = merged;
        pieces.piece[b] = None;
        pieces.join_links(b, a);
        for c in touched {
            pieces.changed[c] = step + 1;
        }
        let around: Vec<usize> = pieces.links[a].keys().copied().collect();
        for c in around {
            let estimate = estimates
                .get(&c)
                .copied()
                .unwrap_or((f64::NEG_INFINITY, f64::NEG_INFINITY));
            candidates.insert(
                (a.min(c), a.max(c)),
                Candidate {
                    piece: None,
                    estimate,
                    measured: None,
                },
            );
        }
    }

    /// Fits the merges of `pairs` that have no fit (side by side), and measures them all on
    /// the pieces as they are at step `step`.
    fn refresh(
        &self,
        pairs: &[(usize, usize)],
        candidates: &mut BTreeMap<(usize, usize), Candidate>,
        pieces: &Pieces,
        step: usize,
    ) -> Result<(), FitError> {
        let tried = run_parallel(
            pairs,
            |&(a, b), _| -> Result<Option<(Option<Part>, (f64, f64))>, FitError> {
                let (Some(pa), Some(pb), Some(c)) =
                    (&pieces.piece[a], &pieces.piece[b], candidates.get(&(a, b)))
                else {
                    return Ok(None);
                };
                let fresh = match &c.piece {
                    Some(_) => None,
                    None => {
                        let mut members = pa.members.clone();
                        members.extend_from_slice(&pb.members);
                        members.sort_unstable();
                        let larger = if pa.members.len() >= pb.members.len() {
                            pa
                        } else {
                            pb
                        };
                        Some(self.piece(members, Initialization::Explicit(larger.pose))?)
                    }
                };
                let merged = fresh.as_ref().or(c.piece.as_ref());
                let estimate = match merged {
                    Some(m) => self.measure(pieces, a, b, m),
                    None => (f64::INFINITY, f64::INFINITY),
                };
                Ok(Some((fresh, estimate)))
            },
            &mut |_: &()| {},
        );
        for (pair, t) in pairs.iter().zip(tried) {
            let Some((fresh, estimate)) = t? else {
                continue;
            };
            if let Some(c) = candidates.get_mut(pair) {
                if fresh.is_some() {
                    c.piece = fresh;
                }
                c.estimate = estimate;
                c.measured = Some(step);
            }
        }
        Ok(())
    }
}

/// Whether candidate `c` for the pair `(a, b)` has a fit and was measured since any piece it is
/// measured on last changed.
fn current(c: &Candidate, pieces: &Pieces, (a, b): (usize, usize)) -> bool {
    match (c.piece.is_some(), c.measured) {
        (true, Some(at)) => pieces.around(a, b).iter().all(|&k| pieces.changed[k] <= at),
        _ => false,
    }
}

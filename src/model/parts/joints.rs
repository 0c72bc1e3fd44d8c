//! Joints between the parts of a whole object that touch ([`PartJoint`]): where two fitted parts
//! overlap or meet, a point-to-point joint ([`crate::model::joint`]) ties them at the middle of
//! their contact, so that the parts move as one jointed model.

use crate::model::fit::FitReport;
use crate::model::init::InitialPose;
use crate::model::joint::JointEnd;
use glam::DVec3;

/// A joint between two parts of a [`super::Partition`]: the parts' indices and the material
/// point on each where they touch.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PartJoint {
    /// The two parts, the lower index first.
    pub parts: [usize; 2],
    /// The joint's end on each part.
    pub ends: [JointEnd; 2],
    /// Where the parts touch (data frame): the middle of their contact.
    pub at: DVec3,
}

/// The joints of the parts `fits` that touch: two parts touch where a node of one lies inside
/// the other, or their surfaces come within `reach` (data units) of each other. The joint sits
/// at the centroid of the contact (the nodes inside the other part, or the closest pair's
/// midpoint), each end at the part's node nearest it. In the order of the parts' indices.
pub fn joints(fits: &[FitReport], reach: f64) -> Vec<PartJoint> {
    let shapes: Vec<(InitialPose, Vec<DVec3>)> = fits
        .iter()
        .map(|f| {
            let mut x = Vec::new();
            f.state.node_positions(&f.tess, &mut x);
            (InitialPose::of(&f.state), x)
        })
        .collect();
    let mut out = Vec::new();
    for a in 0..fits.len() {
        for b in a + 1..fits.len() {
            let (pa, xa) = &shapes[a];
            let (pb, xb) = &shapes[b];
            let contact: Vec<DVec3> = xa
                .iter()
                .filter(|&&x| pb.contains(x))
                .chain(xb.iter().filter(|&&x| pa.contains(x)))
                .copied()
                .collect();
            let at = if contact.is_empty() {
                let closest = xa
                    .iter()
                    .flat_map(|p| xb.iter().map(move |q| (p.distance(*q), (*p + *q) * 0.5)))
                    .min_by(|x, y| x.0.total_cmp(&y.0));
                match closest {
                    Some((d, mid)) if d <= reach => mid,
                    _ => continue,
                }
            } else {
                contact.iter().copied().sum::<DVec3>() / contact.len() as f64
            };
            let end = |j: usize| JointEnd::nearest(&fits[j].tess, &shapes[j].1, at);
            if let (Some(ea), Some(eb)) = (end(a), end(b)) {
                out.push(PartJoint {
                    parts: [a, b],
                    ends: [ea, eb],
                    at,
                });
            }
        }
    }
    out
}

//! Migrating a point of influence along the surface towards the foot of its datum
//! ([`RangeForces::migrate`]), one data point at a time.

use super::*;

/// The fewest points one thread migrates at a time when [`RangeForces::parallel`] is set (about
/// 40 µs of work on the continuous surface).
pub const PARALLEL_MIGRATION: usize = 128;

/// [`RangeForces::migrate`] for one data point `r` whose point of influence is `inf`, with the
/// model's continuous surface and the point's kept [`SurfaceTerms`] when the points lie on it.
/// Returns the point of influence's position.
pub(super) fn migrate_point(
    r: DVec3,
    inf: &mut Influence,
    mut surface: Option<(&ModelSurface, &mut SurfaceTerms)>,
    tess: &Tessellation,
    node_x: &[DVec3],
    rate: f64,
) -> DVec3 {
    // A point reassigned onto a node has no shape-function derivatives there; its
    // element's are the mesh's tangents.
    let located;
    let at = if inf.at.weights[0] == 1.0 {
        located = tess.locate(inf.u, inf.v);
        &located
    } else {
        &inf.at
    };
    let mesh_tangent =
        |d: &[f64; 4]| -> DVec3 { (0..4).map(|k| d[k] * node_x[at.nodes[k] as usize]).sum() };
    let (x, tangents) = match &mut surface {
        Some((s, kept)) => {
            // The terms of the point's (u, v): kept from the last migration unless the
            // point has been reassigned since.
            if kept.u != inf.u || kept.v != inf.v {
                **kept = SurfaceTerms::new(inf.u, inf.v);
            }
            let (x, tangents) = s.with_tangents_terms(&kept.trig, at);
            let on_node = inf.at.weights[0] == 1.0;
            (
                if on_node {
                    node_x[inf.at.nodes[0] as usize]
                } else {
                    x
                },
                tangents,
            )
        }
        None => (inf.at.interpolate(|k| node_x[k]), None),
    };
    let (tu, tv) = tangents.unwrap_or_else(|| (mesh_tangent(&at.du), mesh_tangent(&at.dv)));
    let f = r - x;
    let step = |t: DVec3, h: f64| {
        let t2 = t.length_squared();
        if t2 > 1e-24 {
            (rate * f.dot(t) / t2).clamp(-h, h)
        } else {
            0.0
        }
    };
    let (mut du, mut dv, at_foot) = match surface {
        None => (step(tu, tess.h_u), step(tv, tess.h_v), false),
        Some(_) => {
            // The whole Gauss–Newton move: the superquadric's tangents are not
            // orthogonal, least of all near its edges.
            let (uu, uv, vv) = (tu.dot(tu), tu.dot(tv), tv.dot(tv));
            let (fu, fv) = (f.dot(tu), f.dot(tv));
            let det = uu * vv - uv * uv;
            let (du, dv) = if det > 1e-12 * uu * vv {
                ((vv * fu - uv * fv) / det, (uu * fv - uv * fu) / det)
            } else {
                (step(tu, f64::INFINITY), step(tv, f64::INFINITY))
            };
            // At most one element, in the move's own direction.
            let scale = (tess.h_u / du.abs()).min(tess.h_v / dv.abs()).min(1.0);
            let normal = tu.cross(tv).normalize_or_zero();
            let along = f - f.dot(normal) * normal;
            let at_foot = along.length() <= MIGRATION_AT_FOOT * f.length();
            (rate * scale * du, rate * scale * dv, at_foot)
        }
    };
    let mut foot = x;
    if !at_foot {
        // Descent safeguard: across element edges the mesh's tangents jump, and a full
        // move can overshoot a kink of the faceted surface or a sharp edge of the
        // superquadric; halve it until the distance does not grow.
        let here = f.length_squared();
        for _ in 0..4 {
            let (u, v) = Tessellation::wrap(inf.u + du, inf.v + dv);
            let at = tess.locate(u, v);
            // The trial's terms become the point's if the move is taken. On a node the
            // surface is the node (to rounding, which must not make a point that
            // migration cannot move look farther than its node and be reassigned every
            // time).
            let trial = surface.as_ref().map(|(s, _)| (*s, SurfaceTerms::new(u, v)));
            let moved = match &trial {
                Some((s, t)) if at.weights[0] != 1.0 => s.at_terms(&t.trig, &at),
                _ => at.interpolate(|k| node_x[k]),
            };
            if moved.distance_squared(r) <= here {
                *inf = Influence { u, v, at };
                foot = moved;
                if let (Some((_, t)), Some((_, kept))) = (trial, surface.as_mut()) {
                    **kept = t;
                }
                break;
            }
            du *= 0.5;
            dv *= 0.5;
        }
    }
    foot
}

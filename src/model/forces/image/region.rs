//! A part's own region statistics: what its inside looks like against what lies around it.

/// The intensity model of one part: the luminance of the object it covers and of what lies
/// around it (Chan and Vese's two constants c_in and c_out, measured where the part is, not over
/// the whole image; see [`RegionModel::from_samples`]). The region force pushes the outline out
/// where the image looks like the inside and pulls it in where it looks like the outside.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RegionModel {
    /// Mean luminance inside the part's projected silhouette.
    pub inside: f64,
    /// Mean luminance in a ring around the silhouette.
    pub outside: f64,
}

/// Means closer than this (in luminance, of [0, 1]) tell nothing apart: one 8-bit grey level.
const MIN_CONTRAST: f64 = 1.0 / 255.0;

impl RegionModel {
    /// The model of a part from luminance samples of its projected silhouette (`inside`), of a
    /// ring around it (`ring`) and of its spine (`spine`: the segment between its poles'
    /// projections, which a placement from clicks on the object's axes puts on the object). The
    /// samples of the silhouette and the ring are split in two classes by Otsu's threshold of
    /// their own histogram (a threshold local to the part). The object is the class most of the
    /// spine lies in; when the spine is split evenly (or has no sample), the class that takes a
    /// larger share of the silhouette than of the ring. `inside` is the object class's mean,
    /// `outside` the other's. `None` when the silhouette or the ring has no sample, when one
    /// class is empty, or when nothing tells the object from the rest.
    pub fn from_samples(inside: &[f64], ring: &[f64], spine: &[f64]) -> Option<Self> {
        if inside.is_empty() || ring.is_empty() {
            return None;
        }
        let all: Vec<f64> = inside.iter().chain(ring).copied().collect();
        let t = super::otsu_threshold(&all);
        let bright = |v: &&f64| **v > t;
        let share = |s: &[f64]| s.iter().filter(bright).count() as f64 / s.len() as f64;
        let (mut sums, mut counts) = ([0.0; 2], [0usize; 2]);
        for v in &all {
            let c = usize::from(bright(&v));
            sums[c] += v;
            counts[c] += 1;
        }
        if counts.contains(&0) {
            return None;
        }
        let [dark, light] = [0, 1].map(|c| sums[c] / counts[c] as f64);
        let bright_spine = spine.iter().filter(bright).count();
        let (bright_in, bright_ring) = match (2 * bright_spine).cmp(&spine.len()) {
            std::cmp::Ordering::Equal => (share(inside), share(ring)),
            // The spine's majority decides: as if all of the silhouette were of its class.
            std::cmp::Ordering::Greater => (1.0, 0.0),
            std::cmp::Ordering::Less => (0.0, 1.0),
        };
        if bright_in > bright_ring {
            Some(Self {
                inside: light,
                outside: dark,
            })
        } else if bright_in < bright_ring {
            Some(Self {
                inside: dark,
                outside: light,
            })
        } else {
            None
        }
    }

    /// How much a luminance `lum` looks like the inside: +1 at or beyond the inside's mean, −1 at
    /// or beyond the outside's, linear between. It is Chan–Vese's region term
    /// (I − c_out)² − (I − c_in)² divided by (c_in − c_out)², clamped to [−1, 1], so it is 0 half
    /// way between the means. 0 when the means are within one grey level: no contrast, no push.
    pub fn membership(&self, lum: f64) -> f64 {
        let d = self.inside - self.outside;
        if d.abs() < MIN_CONTRAST || !d.is_finite() {
            return 0.0;
        }
        ((2.0 * lum - self.inside - self.outside) / d).clamp(-1.0, 1.0)
    }

    /// +1 when the inside is darker than the outside (the image brightens outwards across the
    /// part's edge), −1 when it is brighter, 0 when the means are within one grey level.
    pub fn polarity(&self) -> f64 {
        let d = self.outside - self.inside;
        if d.abs() < MIN_CONTRAST || !d.is_finite() {
            0.0
        } else {
            d.signum()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_object_is_the_class_the_part_covers_more_of_than_its_ring() {
        // A thin dark leg on white: the crude part is mostly white, but its ring is whiter.
        let inside: Vec<f64> = (0..100).map(|i| if i < 30 { 0.05 } else { 0.95 }).collect();
        let ring: Vec<f64> = (0..100).map(|i| if i < 5 { 0.05 } else { 0.95 }).collect();
        let dark = |m: Option<RegionModel>| {
            let m = m.unwrap();
            (m.inside - 0.05).abs() < 1e-12 && (m.outside - 0.95).abs() < 1e-12
        };
        assert!(dark(RegionModel::from_samples(&inside, &ring, &[])));
        // An even spine leaves it to the shares too.
        assert!(dark(RegionModel::from_samples(
            &inside,
            &ring,
            &[0.05, 0.95]
        )));
        // The same scene in negative: a bright object on dark.
        let neg = |v: &[f64]| v.iter().map(|x| 1.0 - x).collect::<Vec<_>>();
        let m = RegionModel::from_samples(&neg(&inside), &neg(&ring), &[]).unwrap();
        assert!(
            (m.inside - 0.95).abs() < 1e-12 && (m.outside - 0.05).abs() < 1e-12,
            "{m:?}"
        );
        // A leg between two legs: the ring is darker than the crude part, but the part's spine
        // lies on the leg.
        let between: Vec<f64> = (0..100).map(|i| if i < 50 { 0.05 } else { 0.95 }).collect();
        assert!(!dark(RegionModel::from_samples(&inside, &between, &[])));
        assert!(dark(RegionModel::from_samples(
            &inside,
            &between,
            &[0.05, 0.05, 0.95]
        )));
        // No contrast, no sample, or nothing to tell the object by: no model.
        assert_eq!(RegionModel::from_samples(&[0.5; 10], &[0.5; 10], &[]), None);
        assert_eq!(RegionModel::from_samples(&[], &ring, &[0.05]), None);
        assert_eq!(RegionModel::from_samples(&inside, &inside, &[]), None);
    }

    #[test]
    fn membership_is_chan_vese_s_region_term_scaled_and_clamped() {
        let m = RegionModel {
            inside: 0.2,
            outside: 0.8,
        };
        for lum in [0.0, 0.1, 0.2, 0.35, 0.5, 0.65, 0.8, 1.0] {
            let cv = (lum - m.outside).powi(2) - (lum - m.inside).powi(2);
            let want = (cv / (m.inside - m.outside).powi(2)).clamp(-1.0, 1.0);
            assert!((m.membership(lum) - want).abs() < 1e-12, "{lum}");
        }
        assert_eq!(m.membership(0.2), 1.0);
        assert_eq!(m.membership(0.8), -1.0);
        assert!(m.membership(0.5).abs() < 1e-12);
        assert_eq!(m.polarity(), 1.0);
        let bright = RegionModel {
            inside: 0.9,
            outside: 0.3,
        };
        assert_eq!(bright.membership(1.0), 1.0);
        assert_eq!(bright.membership(0.0), -1.0);
        assert_eq!(bright.polarity(), -1.0);
        let flat = RegionModel {
            inside: 0.5,
            outside: 0.501,
        };
        assert_eq!((flat.membership(0.9), flat.polarity()), (0.0, 0.0));
    }
}

//! What a walk of [`TriangleBvh`] collects: the closest triangle, or the closest few.

use super::{CERTIFIED, TriangleBvh};
use crate::mesh::vec3::{dot, sub};

/// What a tree walk collects from the triangles it is offered.
pub(super) trait Collector {
    /// Squared distance beyond which a box cannot change what is collected.
    fn bound(&self) -> f64;
    /// Offers the triangle in `slot`, whose closest point to the query is `q` at squared distance `d2`.
    fn offer(&mut self, bvh: &TriangleBvh, slot: u32, q: [f64; 3], d2: f64);
}

/// The closest triangle; ties go to the lower triangle index, so the answer does not depend on the
/// order of the offers (nor on a hint).
#[derive(Debug, Clone, Copy)]
pub(super) struct Best {
    pub(super) d2: f64,
    pub(super) slot: Option<u32>,
    pub(super) point: [f64; 3],
}

impl Default for Best {
    fn default() -> Self {
        Best {
            d2: f64::INFINITY,
            slot: None,
            point: [0.0; 3],
        }
    }
}

impl Collector for Best {
    fn bound(&self) -> f64 {
        self.d2
    }

    fn offer(&mut self, bvh: &TriangleBvh, slot: u32, q: [f64; 3], d2: f64) {
        let better = match self.slot {
            None => true,
            Some(b) => {
                d2 < self.d2 || (d2 == self.d2 && bvh.ids[slot as usize] < bvh.ids[b as usize])
            }
        };
        if better {
            *self = Best {
                d2,
                slot: Some(slot),
                point: q,
            };
        }
    }
}

/// The [`CERTIFIED`] + 1 closest triangles, in the order of [`Best`] (distance, then triangle index).
#[derive(Debug, Clone, Copy)]
pub(super) struct Nearest {
    pub(super) items: [(f64, u32, [f64; 3]); CERTIFIED + 1],
    pub(super) count: usize,
}

impl Default for Nearest {
    fn default() -> Self {
        Nearest {
            items: [(f64::INFINITY, 0, [0.0; 3]); CERTIFIED + 1],
            count: 0,
        }
    }
}

impl Collector for Nearest {
    fn bound(&self) -> f64 {
        if self.count > CERTIFIED {
            self.items[CERTIFIED].0
        } else {
            f64::INFINITY
        }
    }

    fn offer(&mut self, bvh: &TriangleBvh, slot: u32, q: [f64; 3], d2: f64) {
        let before = |a: &(f64, u32, [f64; 3])| {
            d2 < a.0 || (d2 == a.0 && bvh.ids[slot as usize] < bvh.ids[a.1 as usize])
        };
        let len = self.count.min(CERTIFIED + 1);
        let at = self.items[..len].iter().position(before).unwrap_or(len);
        if at > CERTIFIED {
            return;
        }
        let end = len.min(CERTIFIED);
        self.items.copy_within(at..end, at + 1);
        self.items[at] = (d2, slot, q);
        self.count += 1;
    }
}

/// Squared distance between two points.
#[inline]
pub(super) fn distance2(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = sub(a, b);
    dot(d, d)
}

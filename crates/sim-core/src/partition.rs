//! A sharded run's geometry and each shard's view: the [`Partition`] of the arena into
//! regions, a copter's [`Role`] in a shard, the [`ShardView`] a `State` keeps, and the zones
//! ownership is decided by ([`PULL_ZONE_M`], [`HELD_ZONE_M`]). The ghost exchange, which reads
//! and writes the `State`, is [`crate::shard`]'s.

use serde::{Deserialize, Serialize};

use crate::math::{Real, Vec3};
use crate::world::World;

/// A shard's number, `0..shards`.
pub type ShardId = u16;

/// How far from its region a copter may be owned by a shard (contact clusters pulled across
/// a border), m. Larger clusters are violations.
pub const PULL_ZONE_M: Real = 3.0;

/// How far from the region of the shard whose Rapier world holds it a copter stays with that
/// shard ([`crate::shard::Ghost::held_by`]), m: a cluster kept there must stay inside the pull zone, with a
/// reservation sphere's reach to spare.
pub const HELD_ZONE_M: Real = PULL_ZONE_M - 1.0;

/// Beyond this distance from a region, a neighbour's copter is sent and held as [`Role::Far`]:
/// the pull zone plus two reservation spheres (no copter this shard may own can meet it).
pub const FAR_BEYOND_M: Real = PULL_ZONE_M + 2.0;

/// What a copter is to one shard.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Role {
    /// Stepped here.
    Owned,
    /// A neighbour's copter within the pull zone (and a margin) of this region, with its
    /// whole state, since this shard may take it over within the step: read, and its wakes
    /// felt here as its owner feels them (its reachable sphere joins the ownership); sensed
    /// and controlled only once taken over.
    Ghost,
    /// A neighbour's copter farther out in the halo: only what others read of it (its motion,
    /// rotor thrusts, crash, sonar timing), neither sensed, controlled nor blown on here.
    Far,
    /// Far away: not read.
    Absent,
}

/// The arena split into `nx × ny` regions of equal size, numbered row by row from
/// `(x0, y0)`. The outer regions extend beyond the walls, so every point has a region.
#[derive(Clone, Debug, PartialEq)]
pub struct Partition {
    nx: u16,
    ny: u16,
    rect: [Real; 4],
    halo_m: Real,
}

/// A sharding setup that cannot work.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ShardError {
    /// No shards, or more than regions can be made of.
    #[error("cannot split the arena into {shards} shards (1..=1024)")]
    Count {
        /// The count asked for.
        shards: usize,
    },
    /// A shard id outside `0..shards`.
    #[error("shard {shard} does not exist: there are {shards} (0..{shards})")]
    Id {
        /// The id given.
        shard: usize,
        /// The count.
        shards: usize,
    },
    /// A ghost for a copter this shard owns: two shards stepped the same copter.
    #[error("copter {copter} arrived as a ghost at tick {tick}, but this shard owns it: two shards stepped it")]
    Duplicate {
        /// Copter id.
        copter: usize,
        /// The tick of the exchange.
        tick: u64,
    },
    /// A ghost whose state no copter can have (a number not finite, a pose or speed out of
    /// reach): a defective or hostile neighbour.
    #[error("the ghost of copter {copter} at tick {tick} is not a copter's state: {what}")]
    BadGhost {
        /// Copter id.
        copter: usize,
        /// The tick of the exchange.
        tick: u64,
        /// What is wrong.
        what: String,
    },
    /// A ghost with an id the scene does not have.
    #[error("a ghost names copter {copter}, but the scene has {copters} copters")]
    Unknown {
        /// The id given.
        copter: usize,
        /// Copters in the scene.
        copters: usize,
    },
}

impl Partition {
    /// Splits `world`'s arena into `shards` regions, as square as the count allows (strips
    /// for 2 or 3 in a square arena, a grid beyond). Same scene and count, same split.
    pub fn new(world: &World, shards: usize) -> Result<Self, ShardError> {
        if shards == 0 || shards > 1024 {
            return Err(ShardError::Count { shards });
        }
        let [w, h] = world.arena.size_m;
        let (mut best, mut best_cost) = ((shards, 1), Real::INFINITY);
        for nx in 1..=shards {
            if !shards.is_multiple_of(nx) {
                continue;
            }
            let ny = shards / nx;
            let aspect = (w / nx as Real) / (h / ny as Real);
            let cost = aspect.ln().abs();
            // Ties: more columns (strips across x).
            if cost < best_cost - 1e-6 || ((cost - best_cost).abs() <= 1e-6 && nx > best.0) {
                (best, best_cost) = ((nx, ny), cost);
            }
        }
        Ok(Self {
            nx: best.0 as u16,
            ny: best.1 as u16,
            rect: [-w / 2.0, -h / 2.0, w / 2.0, h / 2.0],
            halo_m: halo_m(world),
        })
    }

    /// How many shards.
    pub fn shards(&self) -> usize {
        usize::from(self.nx) * usize::from(self.ny)
    }

    /// Columns and rows of regions.
    pub fn grid(&self) -> (u16, u16) {
        (self.nx, self.ny)
    }

    /// How far beyond its region a shard sees other shards' copters, m: the sonar range (or the
    /// longest wake allowed), plus the pull zone and a reservation's reach.
    pub fn halo_m(&self) -> Real {
        self.halo_m
    }

    /// The region holding `p` (points outside the arena: the nearest region).
    pub fn region_of(&self, p: Vec3) -> ShardId {
        let [x0, y0, x1, y1] = self.rect;
        let ix = (((p.x - x0) / (x1 - x0) * Real::from(self.nx)).floor() as i64).clamp(0, i64::from(self.nx) - 1);
        let iy = (((p.y - y0) / (y1 - y0) * Real::from(self.ny)).floor() as i64).clamp(0, i64::from(self.ny) - 1);
        (iy * i64::from(self.nx) + ix) as ShardId
    }

    /// Region `k`'s bounds `[x0, y0, x1, y1]`; the outer ones are unbounded beyond the walls.
    pub fn bounds(&self, k: ShardId) -> [Real; 4] {
        let [x0, y0, x1, y1] = self.rect;
        let (ix, iy) = (k % self.nx, k / self.nx);
        let (w, h) = ((x1 - x0) / Real::from(self.nx), (y1 - y0) / Real::from(self.ny));
        let lo = |i: u16, o: Real, s: Real| if i == 0 { Real::NEG_INFINITY } else { o + Real::from(i) * s };
        let hi = |i: u16, n: u16, o: Real, s: Real| if i + 1 == n { Real::INFINITY } else { o + Real::from(i + 1) * s };
        [lo(ix, x0, w), lo(iy, y0, h), hi(ix, self.nx, x0, w), hi(iy, self.ny, y0, h)]
    }

    /// Horizontal distance from `p` to region `k` (0 inside it), m.
    pub fn distance_to(&self, p: Vec3, k: ShardId) -> Real {
        let [x0, y0, x1, y1] = self.bounds(k);
        let dx = (x0 - p.x).max(p.x - x1).max(0.0);
        let dy = (y0 - p.y).max(p.y - y1).max(0.0);
        // Beside a region (one of the two is 0, always so in a split along one axis) without
        // the libm call: `hypot` of a zero and a non-negative `d` is `d`.
        match (dx == 0.0, dy == 0.0) {
            (true, _) => dy,
            (false, true) => dx,
            (false, false) => dx.hypot(dy),
        }
    }

    /// The shards that exchange ghosts with `k`: those whose regions lie within the halo plus
    /// the pull zone of `k`'s, in id order.
    pub fn neighbours(&self, k: ShardId) -> Vec<ShardId> {
        let [ax0, ay0, ax1, ay1] = self.bounds(k);
        (0..self.shards() as ShardId)
            .filter(|&t| {
                let [bx0, by0, bx1, by1] = self.bounds(t);
                let dx = (bx0 - ax1).max(ax0 - bx1).max(0.0);
                let dy = (by0 - ay1).max(ay0 - by1).max(0.0);
                t != k && dx.hypot(dy) <= self.halo_m + PULL_ZONE_M
            })
            .collect()
    }
}

/// The halo for `world`: what a copter's sonars (with cross-talk) can reach, plus the pull
/// zone and a margin for reservation spheres, m. Wakes longer than the sonar reach are
/// violations (see [`crate::step`]).
pub fn halo_m(world: &World) -> Real {
    PULL_ZONE_M + 1.0 + sense_reach_m(world)
}

/// The farthest another copter's centre can be and still matter to a copter's sonars,
/// cross-talk or downwash within one step, m.
pub(crate) fn sense_reach_m(world: &World) -> Real {
    let sonar = &world.sensors.spec.sonar;
    let body = world.airframes.iter().map(|af| af.radius_m.hypot(af.spec.body_size_m[2])).fold(0.0, Real::max);
    sonar.max_range_m.max(sonar.cap_m) + 2.0 * sonar.mount_offset_m + body
}

/// What a `State` knows about its place in a sharded run (`None` in `State::shard`: one
/// process steps everything).
#[derive(Clone, Debug)]
pub struct ShardView {
    /// This shard.
    pub me: ShardId,
    /// The split.
    pub partition: Partition,
    /// Every copter's role here.
    pub roles: Vec<Role>,
    /// Whether Rapier had each ghost asleep at its owner.
    pub(crate) asleep: Vec<bool>,
    /// Per copter: the shard whose Rapier world moved it in the last step, if one did
    /// ([`crate::shard::Ghost::held_by`]; for this shard's own copters, set when ownership is decided).
    pub(crate) held_by: Vec<Option<ShardId>>,
    /// Per cluster root: the shard holding its lowest held copter, reused.
    pub(crate) claim: Vec<Option<ShardId>>,
    /// Contact-cluster roots (union-find), reused.
    pub(crate) parent: Vec<u32>,
    /// Per cluster root: whether this shard had or takes one of its copters, reused.
    pub(crate) related: Vec<bool>,
}

/// What a snapshot keeps of a [`ShardView`] (it is not part of a serialised [`crate::State`]): the
/// roles after the last step and the sleep flags of the last ghosts. (The holders are not
/// kept: the next ghosts bring theirs, and a shard reads its own from its Rapier world.) The partition is not
/// kept: it follows from the scene and the shard count.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ShardSnapshot {
    /// This shard.
    pub me: ShardId,
    /// The shard count.
    pub shards: u16,
    /// Every copter's role.
    pub roles: Vec<Role>,
    /// Whether Rapier had each ghost asleep at its owner.
    pub asleep: Vec<bool>,
}

impl ShardView {
    pub(crate) fn new(
        me: ShardId,
        partition: Partition,
        roles: Vec<Role>,
        asleep: Vec<bool>,
        held: Vec<Option<ShardId>>,
    ) -> Self {
        let (parent, related, claim) = (Vec::new(), Vec::new(), Vec::new());
        Self { me, partition, roles, asleep, held_by: held, claim, parent, related }
    }
}

/// Whether a shard's Rapier world carries `body` over from its last step: enabled and moving
/// (a flying copter near something, or a wreck with `closed_form = false`), not a disabled
/// free flyer's or a closed-form wreck's fixed body.
pub(crate) fn held_in_rapier(body: &rapier3d::dynamics::RigidBody) -> bool {
    body.is_enabled() && body.is_dynamic()
}

/// Union-find root with path halving.
pub(crate) fn root(parent: &mut [u32], mut i: u32) -> u32 {
    while parent[i as usize] != i {
        let p = parent[parent[i as usize] as usize];
        parent[i as usize] = p;
        i = p;
    }
    i
}

/// Joins the clusters of `a` and `b`; the root is the lower id.
pub(crate) fn union(parent: &mut [u32], a: u32, b: u32) {
    let (ra, rb) = (root(parent, a), root(parent, b));
    if ra != rb {
        let (lo, hi) = if ra < rb { (ra, rb) } else { (rb, ra) };
        parent[hi as usize] = lo;
    }
}

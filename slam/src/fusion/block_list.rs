//! A list of block indices kept small: what a fused keyframe remembers of where it went.
//!
//! The fuser keeps, for every keyframe of the session, the blocks its depth went into, so that
//! it can take it out again when the pose graph moves it. A 640×480 keyframe goes into hundreds
//! to thousands of blocks; at 12 bytes an index that was several kB a keyframe for the whole
//! session (issue 37, docs/tuning.md). The lists come sorted (`integrate::touched_blocks`), so
//! consecutive indices differ by a few units: each coordinate is stored as the zigzag LEB128
//! varint of its difference from the previous index, one byte each in the common case.

use super::block::BlockIndex;

/// Block indices in their order, delta-coded (module docs).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct BlockList {
    bytes: Box<[u8]>,
    len: u32,
}

impl BlockList {
    /// The list of `blocks`, in their order.
    pub fn new(blocks: &[BlockIndex]) -> Self {
        let mut bytes = Vec::with_capacity(3 * blocks.len());
        let mut previous = BlockIndex::default();
        for b in blocks {
            for (c, p) in [(b.x, previous.x), (b.y, previous.y), (b.z, previous.z)] {
                push_varint(&mut bytes, zigzag(c.wrapping_sub(p)));
            }
            previous = *b;
        }
        Self {
            bytes: bytes.into_boxed_slice(),
            len: u32::try_from(blocks.len()).expect("fewer blocks than u32::MAX"),
        }
    }

    /// Number of blocks.
    pub fn len(&self) -> usize {
        self.len as usize
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The blocks, in the order given to [`BlockList::new`].
    pub fn to_vec(&self) -> Vec<BlockIndex> {
        let mut out = Vec::with_capacity(self.len());
        let (mut at, mut previous) = (0, BlockIndex::default());
        for _ in 0..self.len {
            let mut next = |p: i32| p.wrapping_add(unzigzag(read_varint(&self.bytes, &mut at)));
            previous = BlockIndex::new(next(previous.x), next(previous.y), next(previous.z));
            out.push(previous);
        }
        out
    }

    /// Heap bytes held.
    pub fn heap_bytes(&self) -> usize {
        self.bytes.len()
    }
}

fn zigzag(v: i32) -> u32 {
    ((v << 1) ^ (v >> 31)) as u32
}

fn unzigzag(v: u32) -> i32 {
    ((v >> 1) as i32) ^ -((v & 1) as i32)
}

fn push_varint(out: &mut Vec<u8>, mut v: u32) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// Reads the varint at `*at` and moves past it. The bytes are this module's own encoding.
fn read_varint(bytes: &[u8], at: &mut usize) -> u32 {
    let mut v = 0u32;
    for shift in (0..35).step_by(7) {
        let b = bytes[*at];
        *at += 1;
        v |= u32::from(b & 0x7f) << shift;
        if b < 0x80 {
            break;
        }
    }
    v
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn lists_round_trip_in_their_order_including_extreme_indices() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for case in 0..50 {
            let n = rng.random_range(0..300);
            let span = [3, 1000, i32::MAX][case % 3];
            let blocks: Vec<BlockIndex> = (0..n)
                .map(|_| {
                    let mut c = || rng.random_range(-span..=span);
                    BlockIndex::new(c(), c(), c())
                })
                .chain([
                    BlockIndex::new(i32::MIN, i32::MAX, 0),
                    BlockIndex::new(i32::MAX, i32::MIN, -1),
                ])
                .collect();
            let list = BlockList::new(&blocks);
            assert_eq!(list.len(), blocks.len());
            assert_eq!(list.to_vec(), blocks, "case {case}");
        }
        assert!(BlockList::new(&[]).is_empty());
    }

    #[test]
    fn a_sorted_surface_band_takes_about_three_bytes_a_block() {
        // A tilted plane's band, two blocks thick, as `touched_blocks` lists it (sorted).
        let mut blocks: Vec<BlockIndex> = (-20..20)
            .flat_map(|x| (-15..15).flat_map(move |y| (0..2).map(move |k| (x, y, k))))
            .map(|(x, y, k)| BlockIndex::new(x, y, 10 + (x + y) / 4 + k))
            .collect();
        blocks.sort_unstable();
        let list = BlockList::new(&blocks);
        assert_eq!(list.to_vec(), blocks);
        let per_block = list.heap_bytes() as f64 / blocks.len() as f64;
        assert!(per_block <= 3.1, "{per_block} bytes a block");
    }
}

//! A ring of batch-sized slots in shared memory, for a learner on the same host: the producer
//! augments straight into a slot, the learner maps the same memory and reads the batch where it
//! lies, so no observation byte goes through a socket.
//!
//! The memory is a [`MemFile`], as for the workers' frames and acting: the learner receives its
//! descriptor over a Unix socket (the service's hand-off) and checks the header's token. A slot belongs
//! to exactly one holder at a time: the free list, the producer filling it, or the transport until
//! the learner releases it. [`Slot`] is that ownership; dropping it puts the slot back.

use std::io;
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use radserve_shm::MemFile;

/// Bytes 0..16 of the header: what this memory is.
pub const SHARED_MAGIC: &[u8; 16] = b"radserve-batches";
/// The header page before the first slot: the magic, then a 16-byte random token.
pub const SHARED_HEADER_BYTES: usize = 4096;
/// Observation regions start on cache lines.
const REGION_ALIGN: usize = 64;

pub struct SharedRing {
    /// Owned for the ring's life; slots write through `base`, which points into it.
    memory: MemFile,
    base: *mut u8,
    token: [u8; 16],
    slots: usize,
    slot_bytes: usize,
    /// Where each observation region (one per view of a batch) starts in a slot, and its size.
    regions: Vec<(usize, usize)>,
    free: Mutex<Vec<usize>>,
    freed: Condvar,
}

// SAFETY: `base` points into `memory`, which lives as long as the ring; each slot's bytes are written
// only by the one `Slot` that owns its index (the free list hands an index to one owner at a time).
unsafe impl Send for SharedRing {}
// SAFETY: as above; shared access goes through the free list's mutex.
unsafe impl Sync for SharedRing {}

impl SharedRing {
    /// A ring of `slots` slots, each holding one observation region per entry of `region_bytes`
    /// (one per view of a batch), each on a cache line. Pages are allocated by the kernel when
    /// first written.
    pub fn create(slots: usize, region_bytes: &[usize]) -> io::Result<Arc<SharedRing>> {
        let mut regions = Vec::with_capacity(region_bytes.len());
        let mut offset = 0usize;
        for &bytes in region_bytes {
            regions.push((offset, bytes));
            offset = offset.saturating_add(bytes.next_multiple_of(REGION_ALIGN));
        }
        let slot_bytes = offset.max(1).next_multiple_of(SHARED_HEADER_BYTES);
        let len = SHARED_HEADER_BYTES + slots.max(1) * slot_bytes;
        // The learner maps it too, but writes only slots the server has handed it (and the server
        // reads nothing back from it).
        let (mut memory, header) = MemFile::create_with_header(c"radserve-batches", len, SHARED_MAGIC)?;
        let base = memory.as_mut_ptr();
        Ok(Arc::new(SharedRing {
            memory,
            base,
            token: header.token,
            slots,
            slot_bytes,
            regions,
            free: Mutex::new((0..slots).rev().collect()),
            freed: Condvar::new(),
        }))
    }

    /// The memory's descriptor, to hand to the learner.
    pub fn fd(&self) -> std::os::fd::BorrowedFd<'_> {
        self.memory.fd()
    }

    /// Bytes of the memory: the header page and every slot.
    pub fn size_bytes(&self) -> usize {
        SHARED_HEADER_BYTES + self.slots * self.slot_bytes
    }

    pub fn token(&self) -> [u8; 16] {
        self.token
    }

    pub fn slots(&self) -> usize {
        self.slots
    }

    pub fn slot_bytes(&self) -> usize {
        self.slot_bytes
    }

    /// Bytes of each region of a slot.
    pub fn region_bytes(&self) -> Vec<usize> {
        self.regions.iter().map(|&(_, bytes)| bytes).collect()
    }

    /// A free slot, waiting for one while `keep_waiting` says so (checked every 50 ms): None when
    /// it stopped saying so first.
    pub fn acquire(self: &Arc<Self>, keep_waiting: impl Fn() -> bool) -> Option<Slot> {
        let mut free = self.free.lock().expect("slot list lock");
        loop {
            if let Some(index) = free.pop() {
                return Some(Slot { ring: self.clone(), index });
            }
            if !keep_waiting() {
                return None;
            }
            free = self.freed.wait_timeout(free, Duration::from_millis(50)).expect("slot list lock").0;
        }
    }

    /// Slots on the free list now.
    pub fn free_slots(&self) -> usize {
        self.free.lock().expect("slot list lock").len()
    }
}

/// Ownership of one slot; dropping it returns the slot to the ring.
pub struct Slot {
    ring: Arc<SharedRing>,
    index: usize,
}

impl Slot {
    pub fn index(&self) -> usize {
        self.index
    }

    /// Where region `region` starts, from the start of the memory.
    pub fn region_offset(&self, region: usize) -> usize {
        SHARED_HEADER_BYTES + self.index * self.ring.slot_bytes + self.ring.regions[region].0
    }

    /// The first `lens[i]` bytes of region i, for each region, to write a batch into.
    pub fn regions_mut(&mut self, lens: &[usize]) -> Vec<&mut [u8]> {
        assert!(lens.len() <= self.ring.regions.len(), "{} regions asked of a slot of {}", lens.len(), self.ring.regions.len());
        lens.iter()
            .zip(&self.ring.regions)
            .enumerate()
            .map(|(region, (&len, &(_, bytes)))| {
                assert!(len <= bytes, "a view of {len} bytes in a region of {bytes}");
                // SAFETY: the range lies inside this slot's region, inside the mapping (see
                // `create`), and regions do not overlap; this `Slot` is the only owner of its
                // index, and `&mut self` keeps the slices from outliving the borrow or being
                // handed out twice.
                unsafe { std::slice::from_raw_parts_mut(self.ring.base.add(self.region_offset(region)), len) }
            })
            .collect()
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        self.ring.free.lock().expect("slot list lock").push(self.index);
        self.ring.freed.notify_one();
    }
}

impl std::fmt::Debug for Slot {
    fn fmt(&self, formatter: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        formatter.debug_struct("Slot").field("index", &self.index).finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn another_mapping_sees_the_header_and_a_slot_s_bytes() {
        let ring = SharedRing::create(3, &[1000, 1000, 10]).unwrap();
        let mut slot = ring.acquire(|| false).unwrap();
        let mut regions = slot.regions_mut(&[1000, 1000, 10]);
        regions[0].fill(7);
        regions[1].fill(9);
        regions[2].fill(3);
        let peer = MemFile::from_fd(ring.fd().try_clone_to_owned().unwrap()).unwrap();
        let peer = peer.as_slice();
        assert_eq!(peer.len(), ring.size_bytes());
        assert_eq!(&peer[..16], SHARED_MAGIC);
        assert_eq!(peer[16..32], ring.token());
        assert!(peer[slot.region_offset(0)..][..1000].iter().all(|&b| b == 7));
        assert!(peer[slot.region_offset(1)..][..1000].iter().all(|&b| b == 9));
        assert!(peer[slot.region_offset(2)..][..10].iter().all(|&b| b == 3));
        for region in 0..3 {
            assert_eq!(slot.region_offset(region) % REGION_ALIGN, 0);
        }
        assert!(slot.region_offset(1) >= slot.region_offset(0) + 1000);
        assert!(slot.region_offset(2) + 10 <= slot.region_offset(0) + ring.slot_bytes());
    }

    #[test]
    fn slots_are_handed_out_once_and_come_back_when_dropped() {
        let ring = SharedRing::create(2, &[64, 64]).unwrap();
        let first = ring.acquire(|| false).unwrap();
        let second = ring.acquire(|| false).unwrap();
        assert_ne!(first.index(), second.index());
        assert!(ring.acquire(|| false).is_none(), "no third slot in a ring of two");
        let index = first.index();
        drop(first);
        assert_eq!(ring.acquire(|| false).unwrap().index(), index);
    }

    #[test]
    fn a_waiting_acquire_gets_the_slot_another_thread_drops() {
        let ring = SharedRing::create(1, &[64, 64]).unwrap();
        let held = ring.acquire(|| false).unwrap();
        let waiter = {
            let ring = ring.clone();
            std::thread::spawn(move || ring.acquire(|| true).map(|slot| slot.index()))
        };
        std::thread::sleep(Duration::from_millis(20));
        drop(held);
        assert_eq!(waiter.join().unwrap(), Some(0));
    }

    #[test]
    fn tokens_differ_between_rings() {
        assert_ne!(SharedRing::create(1, &[64, 64]).unwrap().token(), SharedRing::create(1, &[64, 64]).unwrap().token());
    }
}

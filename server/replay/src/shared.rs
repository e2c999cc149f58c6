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
    /// Bytes of one observation region (obs, then next_obs after it).
    region_bytes: usize,
    free: Mutex<Vec<usize>>,
    freed: Condvar,
}

// SAFETY: `base` points into `memory`, which lives as long as the ring; each slot's bytes are written
// only by the one `Slot` that owns its index (the free list hands an index to one owner at a time).
unsafe impl Send for SharedRing {}
// SAFETY: as above; shared access goes through the free list's mutex.
unsafe impl Sync for SharedRing {}

impl SharedRing {
    /// A ring of `slots` slots, each holding two observation regions of `region_bytes` (obs and
    /// next_obs). Pages are allocated by the kernel when first written.
    pub fn create(slots: usize, region_bytes: usize) -> io::Result<Arc<SharedRing>> {
        let region_bytes = region_bytes.next_multiple_of(REGION_ALIGN);
        let slot_bytes = (2 * region_bytes).next_multiple_of(SHARED_HEADER_BYTES);
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
            region_bytes,
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

    pub fn region_bytes(&self) -> usize {
        self.region_bytes
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

    /// Where the obs region starts, from the start of the memory.
    pub fn obs_offset(&self) -> usize {
        SHARED_HEADER_BYTES + self.index * self.ring.slot_bytes
    }

    /// Where the next_obs region starts, from the start of the memory.
    pub fn next_obs_offset(&self) -> usize {
        self.obs_offset() + self.ring.region_bytes
    }

    /// The first `len` bytes of the obs and of the next_obs region, to write a batch into.
    pub fn regions_mut(&mut self, len: usize) -> (&mut [u8], &mut [u8]) {
        assert!(len <= self.ring.region_bytes, "a batch of {len} bytes in regions of {}", self.ring.region_bytes);
        // SAFETY: both ranges lie inside this slot, inside the mapping (see `create`), and do not
        // overlap; this `Slot` is the only owner of its index, and `&mut self` keeps the two slices
        // from outliving the borrow or being handed out twice.
        unsafe {
            let obs = self.ring.base.add(self.obs_offset());
            let next_obs = self.ring.base.add(self.next_obs_offset());
            (std::slice::from_raw_parts_mut(obs, len), std::slice::from_raw_parts_mut(next_obs, len))
        }
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
        let ring = SharedRing::create(3, 1000).unwrap();
        let mut slot = ring.acquire(|| false).unwrap();
        let (obs, next_obs) = slot.regions_mut(1000);
        obs.fill(7);
        next_obs.fill(9);
        let peer = MemFile::from_fd(ring.fd().try_clone_to_owned().unwrap()).unwrap();
        let peer = peer.as_slice();
        assert_eq!(peer.len(), ring.size_bytes());
        assert_eq!(&peer[..16], SHARED_MAGIC);
        assert_eq!(peer[16..32], ring.token());
        assert!(peer[slot.obs_offset()..][..1000].iter().all(|&b| b == 7));
        assert!(peer[slot.next_obs_offset()..][..1000].iter().all(|&b| b == 9));
        assert_eq!(slot.obs_offset() % REGION_ALIGN, 0);
        assert_eq!(slot.next_obs_offset() % REGION_ALIGN, 0);
        assert!(slot.next_obs_offset() + 1000 <= slot.obs_offset() + ring.slot_bytes());
    }

    #[test]
    fn slots_are_handed_out_once_and_come_back_when_dropped() {
        let ring = SharedRing::create(2, 64).unwrap();
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
        let ring = SharedRing::create(1, 64).unwrap();
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
        assert_ne!(SharedRing::create(1, 64).unwrap().token(), SharedRing::create(1, 64).unwrap().token());
    }
}

//! What a transport keeps while it delivers a producer's batches: heap buffers it hands back once
//! sent, and the shared-memory slots a learner holds until it releases them. No transport here: the
//! gRPC handlers drive these.

use std::collections::HashMap;
use std::sync::Arc;

use crate::error::{ReplayError, Result};
use crate::producer::Recycler;
use crate::shared::Slot;

/// Observation buffers of sent batches, returned to their producer once nothing being sent refers
/// to them any more (the transport's messages slice them without copying).
pub struct InFlight {
    buffers: Vec<Arc<Vec<u8>>>,
    recycler: Recycler,
}

impl InFlight {
    pub fn new(recycler: Recycler) -> InFlight {
        InFlight { buffers: Vec::new(), recycler }
    }

    /// Buffers that messages being sent still share.
    pub fn track(&mut self, buffers: impl IntoIterator<Item = Arc<Vec<u8>>>) {
        self.buffers.extend(buffers);
    }

    /// Hands back every tracked buffer no message refers to now.
    pub fn recycle(&mut self) {
        let mut index = 0;
        while index < self.buffers.len() {
            if Arc::strong_count(&self.buffers[index]) == 1 {
                if let Ok(buffer) = Arc::try_unwrap(self.buffers.swap_remove(index)) {
                    // The producer is gone when this fails: the buffer is just freed.
                    let _ = self.recycler.send(buffer);
                }
            } else {
                index += 1;
            }
        }
    }

    /// Buffers still tracked.
    pub fn len(&self) -> usize {
        self.buffers.len()
    }

    pub fn is_empty(&self) -> bool {
        self.buffers.is_empty()
    }
}

/// The slots of the batches a learner holds: sent to it and not yet released. Dropping a slot hands
/// it back to the producer.
#[derive(Debug, Default)]
pub struct HeldSlots(HashMap<u64, Slot>);

impl HeldSlots {
    /// Batch `index` was sent in `slot`.
    pub fn hold(&mut self, index: u64, slot: Slot) {
        self.0.insert(index, slot);
    }

    /// The learner is done with batch `index`: its slot goes back to the producer. A batch it does
    /// not hold is its mistake, answered with the batches it does hold.
    pub fn release(&mut self, index: u64) -> Result<()> {
        if self.0.remove(&index).is_some() {
            return Ok(());
        }
        let mut holding: Vec<u64> = self.0.keys().copied().collect();
        holding.sort_unstable();
        Err(ReplayError::InvalidArgument(format!(
            "release of batch {index}, which the client does not hold (it holds {holding:?})"
        )))
    }

    pub fn len(&self) -> usize {
        self.0.len()
    }

    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shared::SharedRing;

    #[test]
    fn buffers_come_back_once_no_message_refers_to_them() {
        let (recycler, returned) = std::sync::mpsc::channel();
        let mut in_flight = InFlight::new(recycler);
        let (sent, still_sending) = (Arc::new(vec![1u8; 8]), Arc::new(vec![2u8; 8]));
        let message = still_sending.clone();
        in_flight.track([sent, still_sending]);
        in_flight.recycle();
        assert_eq!(returned.try_iter().collect::<Vec<_>>(), vec![vec![1u8; 8]]);
        assert_eq!(in_flight.len(), 1);
        drop(message);
        in_flight.recycle();
        assert_eq!(returned.try_iter().collect::<Vec<_>>(), vec![vec![2u8; 8]]);
        assert!(in_flight.is_empty());
    }

    #[test]
    fn released_slots_return_and_unknown_releases_are_refused() {
        let ring = SharedRing::create(2, &[64, 64]).unwrap();
        let mut held = HeldSlots::default();
        held.hold(7, ring.acquire(|| false).unwrap());
        held.hold(9, ring.acquire(|| false).unwrap());
        assert_eq!(ring.free_slots(), 0);
        let error = held.release(8).unwrap_err().to_string();
        assert_eq!(error, "release of batch 8, which the client does not hold (it holds [7, 9])");
        held.release(7).unwrap();
        assert_eq!((ring.free_slots(), held.len()), (1, 1));
        assert!(held.release(7).is_err(), "a batch is released once");
    }
}

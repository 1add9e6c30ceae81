//! A slave that plays a script: each request to its own address gets the next planned
//! transmission, or silence. For tests of what the master does with late, foreign, corrupt and
//! missing replies; broadcasts use up no step of the script.

use super::{Simulated, Transmission};
use crate::line::BROADCAST;
use std::collections::VecDeque;
use tokio::time::Instant;

/// A slave that answers from a script: one planned transmission (or silence) per request heard.
pub struct Scripted {
    plan: VecDeque<Option<Transmission>>,
}

impl Scripted {
    /// `None` in the plan: stay silent for that request. After the plan: silent.
    pub fn new(plan: impl IntoIterator<Item = Option<Transmission>>) -> Self {
        Scripted {
            plan: plan.into_iter().collect(),
        }
    }
}

impl Simulated for Scripted {
    fn handle(&mut self, address: u8, _: &[u8], _: Instant) -> Option<Transmission> {
        if address == BROADCAST {
            return None;
        }
        self.plan.pop_front().flatten()
    }
}

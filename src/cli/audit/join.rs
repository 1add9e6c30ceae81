//! Joining each `write` line of the journal to its `outcome` line, across rotations and runs,
//! into the items to print, in the journal's order. Knows nothing of files or of printing.

use crate::audit::entry::{Ended, Gap, Line, Write};
use std::collections::{HashMap, VecDeque};

/// One thing to print, in the journal's order: a write, or a gap in the journal.
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum Item {
    Write(Box<Record>),
    Gap(Gap),
}

/// A write and how it ended, as far as the journal says.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Record {
    pub(crate) write: Write,
    pub(crate) end: End,
}

#[derive(Clone, Debug, PartialEq)]
pub(crate) enum End {
    Recorded(Ended),
    /// A later `open`: the gateway stopped before it wrote the outcome.
    Stopped,
    /// Nothing yet: its outcome may still come, or the gateway stopped with no run after.
    Waiting,
}

/// Joins each `write` line to its `outcome`, which may come many lines (and a rotation) later,
/// and hands the items back in the journal's order once each is whole: a write when it has its
/// outcome or its run ended, a gap at once (behind the writes before it).
#[derive(Default)]
pub(crate) struct Joiner {
    queue: VecDeque<Item>,
    /// How many items have left the queue: an item's number less this is its place in it.
    handed: u64,
    /// The writes of this run still waiting for their outcome, by id: their item's number.
    waiting: HashMap<u64, u64>,
    /// Outcome lines that name no waiting write of their run.
    orphans: u64,
    /// The process of this run, from its `open` line.
    pid: Option<u32>,
    /// The highest write id of this run so far.
    last_id: u64,
    /// An `open` by this run's process (or the first one met) came last: a reload that moved
    /// the journal back here, ids going on, or a restart that got the same pid (in a container,
    /// say), ids from 1 again. The next write's id tells which.
    reopened: bool,
}

/// A line that is not one of the journal's.
#[derive(Debug, PartialEq)]
pub(crate) struct Unreadable;

impl Joiner {
    /// Take one line of the journal (its newline optional).
    pub(crate) fn feed(&mut self, bytes: &[u8]) -> Result<(), Unreadable> {
        let bytes = bytes.strip_suffix(b"\n").unwrap_or(bytes);
        let line = serde_json::from_slice::<Line>(bytes).map_err(|_| Unreadable)?;
        match line {
            Line::Open(opened) => {
                if self.pid.is_some_and(|pid| pid != opened.pid) {
                    self.new_run();
                } else {
                    self.reopened = true;
                }
                self.pid = Some(opened.pid);
            }
            Line::Write(write) => {
                if std::mem::take(&mut self.reopened) && write.id <= self.last_id {
                    self.new_run();
                }
                self.last_id = self.last_id.max(write.id);
                let number = self.handed + self.queue.len() as u64;
                // The same id again in one run: its `open` line is missing, so the earlier
                // write's run ended without its outcome.
                if let Some(earlier) = self.waiting.insert(write.id, number) {
                    self.end(earlier, End::Stopped);
                }
                self.queue.push_back(Item::Write(Box::new(Record {
                    write,
                    end: End::Waiting,
                })));
            }
            Line::Outcome(ended) => match self.waiting.remove(&ended.id) {
                Some(number) => self.end(number, End::Recorded(ended)),
                None => self.orphans += 1,
            },
            Line::Gap(gap) => self.queue.push_back(Item::Gap(gap)),
        }
        Ok(())
    }

    /// A new run began: the writes of the last one still waiting never got their outcome.
    fn new_run(&mut self) {
        for (_, number) in std::mem::take(&mut self.waiting) {
            self.end(number, End::Stopped);
        }
        self.last_id = 0;
    }

    /// Say how the write numbered `number`, still queued, ended.
    fn end(&mut self, number: u64, end: End) {
        let place = number
            .checked_sub(self.handed)
            .and_then(|place| usize::try_from(place).ok());
        if let Some(Item::Write(record)) = place.and_then(|place| self.queue.get_mut(place)) {
            record.end = end;
        }
    }

    /// The items that are whole, from the front of the queue.
    pub(crate) fn ready(&mut self) -> Vec<Item> {
        let mut ready = Vec::new();
        while let Some(front) = self.queue.front() {
            if matches!(front, Item::Write(record) if record.end == End::Waiting) {
                break;
            }
            ready.extend(self.queue.pop_front());
            self.handed += 1;
        }
        ready
    }

    /// Every item left, at the end of the journal (writes still waiting have no outcome yet),
    /// and how many outcome lines named no write.
    pub(crate) fn finish(self) -> (Vec<Item>, u64) {
        (self.queue.into(), self.orphans)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::audit::fixtures::*;
    use crate::cli::audit::print::{as_json, describe};

    #[test]
    fn a_write_is_joined_to_its_outcome_in_the_next_file_after_a_rotation() {
        let older = format!(
            "{OPEN}\n{}\n{}\n",
            write(1, "2026-11-28T10:15:02.123456Z"),
            write(2, "2026-11-28T10:15:03.000000Z")
        );
        let newer = format!("{}\n{}\n", outcome(2, "answered"), outcome(1, "answered"));
        let (items, unreadable) = join(&[&older, &newer]);
        assert!(unreadable.is_empty());
        assert_eq!(
            ids_and_ends(&items),
            [(1, "answered".to_owned()), (2, "answered".to_owned())],
            "in the order of the write lines, each with its own outcome"
        );
        assert_eq!(
            describe(&items[0]),
            "2026-11-28T10:15:02.123456Z  192.168.20.5:50312 tcp  unit 3 -> line1 slave 3  \
             Write Multiple Registers (0x10) holding 0x2000-0x2001 = 1388 0032  rule wallbox: \
             allow  answered"
        );
    }

    #[test]
    fn a_run_restart_leaves_the_earlier_write_without_outcome_and_ids_start_again() {
        let text = format!(
            "{OPEN}\n{}\n{}\n{}\n{}\n{}\n{}\n",
            write(1, "2026-11-28T10:15:02.000000Z"),
            write(2, "2026-11-28T10:15:03.000000Z"),
            open(813),
            write(1, "2026-11-28T11:00:00.000000Z"),
            outcome(1, "answered"),
            write(2, "2026-11-28T11:00:01.000000Z"),
        );
        let (items, _) = join(&[&text]);
        let stopped = "no outcome recorded: may have been carried out \
                       (the gateway stopped before its outcome)";
        let not_yet = "no outcome recorded: may have been carried out (no outcome yet)";
        assert_eq!(
            ids_and_ends(&items),
            [
                (1, stopped.to_owned()),
                (2, stopped.to_owned()),
                (1, "answered".to_owned()),
                (2, not_yet.to_owned()),
            ],
            "the second run's outcome of id 1 is not the first run's"
        );
        let json: serde_json::Value = serde_json::from_str(&as_json(&items[0])).unwrap();
        assert_eq!(json["outcome"], serde_json::Value::Null);
        assert_eq!(json["pending"], "gateway_stopped");
        assert_eq!(json["id"], 1);
        assert_eq!(json["values"], "13880032");
    }

    #[test]
    fn an_open_by_the_same_process_goes_on_with_its_run_unless_the_ids_start_again() {
        // A reload moved the journal away and back: the same pid, the ids going on, and an
        // outcome of a write from before it.
        let reload = format!(
            "{OPEN}\n{}\n{}\n{}\n{}\n",
            write(1, "2026-11-28T10:15:02.000000Z"),
            open(812),
            write(7, "2026-11-28T11:00:01.000000Z"),
            outcome(1, "answered"),
        );
        let (items, _) = join(&[&reload]);
        let not_yet = "no outcome recorded: may have been carried out (no outcome yet)";
        assert_eq!(
            ids_and_ends(&items),
            [(1, "answered".to_owned()), (7, not_yet.to_owned())]
        );
        // A restart that got the same pid (pid 1 in a container): the ids start again.
        let restart = format!(
            "{}\n{}\n{}\n{}\n{}\n",
            open(1),
            write(1, "2026-11-28T10:15:02.000000Z"),
            write(2, "2026-11-28T10:15:03.000000Z"),
            open(1),
            write(1, "2026-11-28T11:00:01.000000Z"),
        );
        let (items, _) = join(&[&restart]);
        let stopped = "no outcome recorded: may have been carried out \
                       (the gateway stopped before its outcome)";
        assert_eq!(
            ids_and_ends(&items),
            [
                (1, stopped.to_owned()),
                (2, stopped.to_owned()),
                (1, not_yet.to_owned())
            ]
        );
    }

    #[test]
    fn a_write_waiting_for_its_outcome_holds_back_the_later_ones_until_it_ends() {
        let mut joiner = Joiner::default();
        joiner
            .feed(write(1, "2026-11-28T10:00:01Z").as_bytes())
            .unwrap();
        joiner
            .feed(write(2, "2026-11-28T10:00:02Z").as_bytes())
            .unwrap();
        joiner.feed(outcome(2, "answered").as_bytes()).unwrap();
        assert!(joiner.ready().is_empty(), "1 comes first");
        joiner.feed(outcome(1, "timeout").as_bytes()).unwrap();
        let ready = joiner.ready();
        assert_eq!(ids_and_ends(&ready).len(), 2);
        joiner.feed(outcome(9, "answered").as_bytes()).unwrap();
        assert_eq!(
            joiner.finish(),
            (Vec::new(), 1),
            "an outcome without its write"
        );
    }

    #[test]
    fn an_unreadable_line_is_counted_and_skipped() {
        let text = format!(
            "{OPEN}\n{}\nnot json\n{{\"kind\":\"write\",\"id\":2}}\n{{\"kind\":\"weird\"}}\n\n{}\n",
            write(1, "2026-11-28T10:15:02.000000Z"),
            outcome(1, "answered"),
        );
        let (items, unreadable) = join(&[&text]);
        assert_eq!(unreadable, ["file0:3", "file0:4", "file0:5", "file0:6"]);
        assert_eq!(ids_and_ends(&items), [(1, "answered".to_owned())]);
        let mut joiner = Joiner::default();
        assert_eq!(
            joiner.feed(&[0xFF, 0xFE, b'\n']),
            Err(Unreadable),
            "not UTF-8"
        );
    }

    #[test]
    fn a_gap_is_its_own_line_in_its_place() {
        let gap = r#"{"kind":"gap","time":"2026-11-28T10:20:00.000000Z","since":"2026-11-28T10:16:00.000000Z","unrecorded":0,"refused":3,"lost_outcomes":1,"error":"No space left on device (os error 28)"}"#;
        let text = format!(
            "{}\n{}\n{gap}\n{}\n{}\n",
            write(1, "2026-11-28T10:15:02.000000Z"),
            outcome(1, "answered"),
            write(2, "2026-11-28T10:21:00.000000Z"),
            outcome(2, "answered"),
        );
        let (items, _) = join(&[&text]);
        assert_eq!(items.len(), 3);
        assert_eq!(
            describe(&items[1]),
            "2026-11-28T10:20:00.000000Z  gap: the journal could not be written from \
             2026-11-28T10:16:00.000000Z: No space left on device (os error 28); 3 writes \
             refused (0x0A), 1 outcome line lost"
        );
        let json: serde_json::Value = serde_json::from_str(&as_json(&items[1])).unwrap();
        assert_eq!(json["kind"], "gap");
        assert_eq!(json["refused"], 3);
        // Shown whatever the other filters, when its time overlaps the window.
        let other = filter(&[("unit", "9"), ("since", "2026-11-28T10:19:00Z")]).unwrap();
        assert!(other.shows(&items[1]));
        assert!(!other.shows(&items[0]) && !other.shows(&items[2]), "unit 3");
        let after = filter(&[("since", "2026-11-28T10:20:01Z")]).unwrap();
        assert!(!after.shows(&items[1]));
        let before = filter(&[("until", "2026-11-28 10:15:59")]).unwrap();
        assert!(!before.shows(&items[1]));
        let during = filter(&[("until", "2026-11-28 10:17:00")]).unwrap();
        assert!(during.shows(&items[1]));
    }
}

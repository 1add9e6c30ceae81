//! Joining each `write` line of the journal to its `outcome` line, across rotations and runs,
//! into the items to print, in the journal's order, holding a bounded number of them. Knows
//! nothing of files or of printing.

use crate::audit::entry::{Ended, Gap, Line, Write};
use std::collections::{HashMap, HashSet, VecDeque};

/// How many items (writes and gaps) may wait behind a write whose outcome has not come, before
/// that write is handed out without it, as pending: the listing goes on, and memory stays
/// bounded (10,000 writes are some 8 MB), whatever the journal holds. An outcome comes when
/// its write ends: after its `queue_timeout` at most, then its `response_timeout` per attempt,
/// seconds. Only a flood of thousands of writes a second fits 10,000 in that time: a write
/// still without its outcome 10,000 writes later has lost it (a journal cut short; a full disk
/// says so sooner, see [`Gap::lost_outcomes`]). Should it come all the same, it is counted in
/// [`Unprinted::late`], not printed twice.
pub(crate) const MAX_HELD: usize = 10_000;

/// How many bytes of journal lines the items held may take, for a journal of long lines (a
/// long certificate subject in each write): the same bound, in memory.
pub(crate) const MAX_HELD_BYTES: usize = 8 << 20;

/// One thing to print, in the journal's order: a write, or a gap in the journal.
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum Listed {
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
    /// A `gap` after it says its outcome line could not be written.
    Lost,
    /// Nothing yet: its outcome may still come, or the gateway stopped with no run after; or
    /// [`MAX_HELD`] writes came after it without it.
    Waiting,
}

/// What was read but not printed, for the summary.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct Unprinted {
    /// Outcome lines that name no write of their run.
    pub(crate) orphans: u64,
    /// Outcome lines of writes already handed out as pending.
    pub(crate) late: u64,
}

/// Joins each `write` line to its `outcome`, which may come many lines (and a rotation) later,
/// and hands the items back in the journal's order once each is whole: a write when it has its
/// outcome, its run ended, a gap said its outcome was lost, or [`MAX_HELD`] items wait behind
/// it; a gap at once (behind the writes before it).
#[derive(Default)]
pub(crate) struct Joiner {
    queue: VecDeque<Held>,
    /// The bytes of the lines of the items queued.
    held_bytes: usize,
    /// How many items have left the queue: an item's number less this is its place in it.
    handed: u64,
    /// The writes of this run still waiting for their outcome, by id.
    waiting: HashMap<u64, Waiting>,
    /// How many of them were waiting when a gap that lost outcome lines came.
    before_gap: u64,
    /// Outcome lines such gaps lost, of writes among those.
    lost: u64,
    /// Writes of this run handed out without their outcome, by id (the last [`MAX_HELD`]):
    /// an outcome line that comes for one later is counted, not printed again.
    given_up: HashSet<u64>,
    given_up_order: VecDeque<u64>,
    tally: Unprinted,
    /// The process of this run, from its `open` line.
    pid: Option<u32>,
    /// The highest write id of this run so far.
    last_id: u64,
    /// An `open` by this run's process (or the first one met) came last: a reload that moved
    /// the journal back here, ids going on, or a restart that got the same pid (in a container,
    /// say), ids from 1 again. The next write's id tells which.
    reopened: bool,
}

/// An item in the queue, and the length of its line.
struct Held {
    item: Listed,
    bytes: usize,
}

/// A write waiting for its outcome.
#[derive(Clone, Copy)]
struct Waiting {
    /// Its item's number.
    number: u64,
    /// It was waiting when a gap that lost outcome lines came.
    before_gap: bool,
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
            Line::Write(write) => self.write(write, bytes.len()),
            Line::Outcome(ended) => match self.waiting.remove(&ended.id) {
                Some(waiting) => {
                    self.end(waiting.number, End::Recorded(ended));
                    if waiting.before_gap {
                        self.before_gap -= 1;
                        self.settle();
                    }
                }
                None if self.given_up.remove(&ended.id) => self.tally.late += 1,
                None => self.tally.orphans += 1,
            },
            Line::Gap(gap) => {
                let lost = gap.lost_outcomes;
                self.push(Listed::Gap(gap), bytes.len());
                if lost > 0 {
                    self.outcomes_lost(lost);
                }
            }
        }
        Ok(())
    }

    fn write(&mut self, write: Write, bytes: usize) {
        if std::mem::take(&mut self.reopened) && write.id <= self.last_id {
            self.new_run();
        }
        self.last_id = self.last_id.max(write.id);
        let waiting = Waiting {
            number: self.handed + self.queue.len() as u64,
            before_gap: false,
        };
        self.given_up.remove(&write.id);
        // The same id again in one run: its `open` line is missing, so the earlier write's
        // run ended without its outcome.
        if let Some(earlier) = self.waiting.insert(write.id, waiting) {
            self.end(earlier.number, End::Stopped);
            if earlier.before_gap {
                self.before_gap -= 1;
            }
        }
        let record = Record {
            write,
            end: End::Waiting,
        };
        self.push(Listed::Write(Box::new(record)), bytes);
    }

    fn push(&mut self, item: Listed, bytes: usize) {
        self.held_bytes += bytes;
        self.queue.push_back(Held { item, bytes });
    }

    /// A gap lost `count` outcome lines: each of a write written before it, so of one of the
    /// writes waiting now (or of one in a file no longer kept). Those not lost are still under
    /// way, and their outcomes come after the gap.
    fn outcomes_lost(&mut self, count: u64) {
        // After a gap they all are: only writes since the last one need marking.
        if self.before_gap < self.waiting.len() as u64 {
            for waiting in self.waiting.values_mut() {
                if !waiting.before_gap {
                    waiting.before_gap = true;
                    self.before_gap += 1;
                }
            }
        }
        self.lost += count;
        self.settle();
    }

    /// Once the writes waiting since a gap are no more than the outcome lines lost, none of
    /// them will get its outcome: each is handed out as lost.
    fn settle(&mut self) {
        if self.before_gap > self.lost {
            return;
        }
        if self.before_gap == 0 {
            // The lines lost were of writes no longer waiting, or in a file no longer kept.
            self.lost = 0;
            return;
        }
        let lost: Vec<(u64, u64)> = self
            .waiting
            .iter()
            .filter(|(_, waiting)| waiting.before_gap)
            .map(|(&id, waiting)| (id, waiting.number))
            .collect();
        for (id, number) in lost {
            self.waiting.remove(&id);
            self.end(number, End::Lost);
            self.give_up(id);
        }
        (self.before_gap, self.lost) = (0, 0);
    }

    /// The write `id` is handed out without its outcome: one that comes later is late.
    fn give_up(&mut self, id: u64) {
        if self.given_up.insert(id) {
            self.given_up_order.push_back(id);
        }
        if self.given_up_order.len() > MAX_HELD {
            if let Some(oldest) = self.given_up_order.pop_front() {
                self.given_up.remove(&oldest);
            }
        }
    }

    /// A new run began: the writes of the last one still waiting never got their outcome.
    fn new_run(&mut self) {
        for (_, waiting) in std::mem::take(&mut self.waiting) {
            self.end(waiting.number, End::Stopped);
        }
        (self.before_gap, self.lost) = (0, 0);
        self.given_up.clear();
        self.given_up_order.clear();
        self.last_id = 0;
    }

    /// Say how the write numbered `number`, still queued, ended.
    fn end(&mut self, number: u64, end: End) {
        let place = number
            .checked_sub(self.handed)
            .and_then(|place| usize::try_from(place).ok());
        let held = place.and_then(|place| self.queue.get_mut(place));
        if let Some(Held {
            item: Listed::Write(record),
            ..
        }) = held
        {
            record.end = end;
        }
    }

    /// The id of the write at the front of the queue if it still waits for its outcome.
    fn front_waiting(&self) -> Option<u64> {
        let Listed::Write(record) = &self.queue.front()?.item else {
            return None;
        };
        let id = record.write.id;
        let waiting = self.waiting.get(&id)?;
        (waiting.number == self.handed).then_some(id)
    }

    /// The items that are whole, from the front of the queue; and the write at its front
    /// without its outcome, if too much waits behind it.
    pub(crate) fn ready(&mut self) -> Vec<Listed> {
        let mut ready = Vec::new();
        while !self.queue.is_empty() {
            if let Some(id) = self.front_waiting() {
                if self.queue.len() <= MAX_HELD && self.held_bytes <= MAX_HELD_BYTES {
                    break;
                }
                if self.waiting.remove(&id).is_some_and(|w| w.before_gap) {
                    // Waiting since a gap that lost outcomes, and still none: one of those.
                    self.before_gap -= 1;
                    self.lost = self.lost.saturating_sub(1);
                    self.settle();
                }
                self.give_up(id);
            }
            if let Some(held) = self.queue.pop_front() {
                self.held_bytes -= held.bytes;
                self.handed += 1;
                ready.push(held.item);
            }
        }
        ready
    }

    /// Every item left, at the end of the journal (writes still waiting have no outcome yet),
    /// and what was read but not printed.
    pub(crate) fn finish(self) -> (Vec<Listed>, Unprinted) {
        let items = self.queue.into_iter().map(|held| held.item).collect();
        (items, self.tally)
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
        let orphan = Unprinted {
            orphans: 1,
            late: 0,
        };
        assert_eq!(
            joiner.finish(),
            (Vec::new(), orphan),
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

    /// The ids of the writes in `items`, each with whether it had its outcome.
    fn ids_answered(items: &[Listed]) -> Vec<(u64, bool)> {
        let answered = |end: &End| matches!(end, End::Recorded(_));
        items
            .iter()
            .filter_map(|item| match item {
                Listed::Write(record) => Some((record.write.id, answered(&record.end))),
                Listed::Gap(_) => None,
            })
            .collect()
    }

    #[test]
    fn a_write_without_outcome_is_handed_out_pending_after_the_bound_not_at_the_end() {
        let mut joiner = Joiner::default();
        joiner.feed(OPEN.as_bytes()).unwrap();
        joiner
            .feed(write(1, "2026-11-28T10:00:01Z").as_bytes())
            .unwrap();
        let mut out = Vec::new();
        let last = MAX_HELD as u64 + 2;
        for id in 2..=last {
            joiner
                .feed(write(id, "2026-11-28T10:00:02Z").as_bytes())
                .unwrap();
            joiner.feed(outcome(id, "answered").as_bytes()).unwrap();
            out.extend(joiner.ready());
            assert!(
                joiner.queue.len() <= MAX_HELD,
                "{id}: held within the bound"
            );
        }
        let mut expected = vec![(1, false)];
        expected.extend((2..=last).map(|id| (id, true)));
        assert_eq!(
            ids_answered(&out),
            expected,
            "all out, in order, before the end"
        );
        assert_eq!(
            ending(&out[0]),
            "no outcome recorded: may have been carried out (no outcome yet)"
        );
        // Its outcome after all: counted, not printed twice.
        joiner.feed(outcome(1, "answered").as_bytes()).unwrap();
        assert!(joiner.ready().is_empty());
        let late = Unprinted {
            orphans: 0,
            late: 1,
        };
        assert_eq!(joiner.finish(), (Vec::new(), late));
    }

    #[test]
    fn writes_of_long_lines_are_held_within_the_bound_in_bytes() {
        let mut joiner = Joiner::default();
        joiner
            .feed(write(1, "2026-11-28T10:00:01Z").as_bytes())
            .unwrap();
        let long = |id: u64| {
            let subject = "x".repeat(MAX_HELD_BYTES / 100);
            write(id, "2026-11-28T10:00:02Z").replace(
                r#""protocol":"tcp""#,
                &format!(r#""protocol":"tls","subject":"{subject}""#),
            )
        };
        let mut out = Vec::new();
        for id in 2..=200 {
            joiner.feed(long(id).as_bytes()).unwrap();
            joiner.feed(outcome(id, "answered").as_bytes()).unwrap();
            out.extend(joiner.ready());
            assert!(joiner.held_bytes <= MAX_HELD_BYTES + long(id).len(), "{id}");
        }
        // 200 writes are far fewer than MAX_HELD: the bytes let them out.
        let mut expected = vec![(1, false)];
        expected.extend((2..=200).map(|id| (id, true)));
        assert_eq!(ids_answered(&out), expected);
    }

    /// What `ending` says of the write `item`.
    fn ending(item: &Listed) -> String {
        match item {
            Listed::Write(record) => crate::cli::audit::print::ending(record),
            Listed::Gap(_) => panic!("a gap"),
        }
    }

    #[test]
    fn a_gap_that_lost_outcomes_hands_out_the_writes_it_leaves_without_one() {
        let gap = |lost: u64| {
            format!(
                r#"{{"kind":"gap","time":"2026-11-28T10:20:00Z","since":"2026-11-28T10:16:00Z","unrecorded":0,"refused":0,"lost_outcomes":{lost},"error":"No space left on device (os error 28)"}}"#
            )
        };
        let mut joiner = Joiner::default();
        let mut feed = |line: String| {
            joiner.feed(line.as_bytes()).unwrap();
            joiner.ready()
        };
        feed(OPEN.to_owned());
        feed(write(1, "2026-11-28T10:15:00Z"));
        // Under way through the gap: its outcome comes after it.
        feed(write(2, "2026-11-28T10:16:00Z"));
        assert!(
            feed(gap(1)).is_empty(),
            "1 or 2 lost its outcome: which, 2's tells"
        );
        let out = feed(outcome(2, "answered"));
        assert_eq!(ids_answered(&out), [(1, false), (2, true)]);
        assert_eq!(
            ending(&out[0]),
            "no outcome recorded: may have been carried out (its outcome line was lost: see \
             the gap after it)"
        );
        assert!(matches!(out[2], Listed::Gap(_)));
        let json: serde_json::Value =
            serde_json::from_str(&crate::cli::audit::print::as_json(&out[0])).unwrap();
        assert_eq!(json["pending"], "outcome_lost");
        // A gap that lost as many outcomes as there are writes waiting: all of them, at once.
        feed(write(3, "2026-11-28T10:21:00Z"));
        feed(write(4, "2026-11-28T10:21:01Z"));
        let out = feed(gap(2));
        assert_eq!(ids_answered(&out), [(3, false), (4, false)]);
        // An outcome line after all: counted, not printed again.
        assert!(feed(outcome(4, "answered")).is_empty());
        feed(write(5, "2026-11-28T10:22:00Z"));
        assert!(feed(gap(0)).is_empty(), "lost none: 5 is still under way");
        let late = Unprinted {
            orphans: 0,
            late: 1,
        };
        let (rest, tally) = joiner.finish();
        assert_eq!((ids_answered(&rest), tally), (vec![(5, false)], late));
    }
}

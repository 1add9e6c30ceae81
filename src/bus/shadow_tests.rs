use super::*;

const MAX_AGE: Duration = Duration::from_secs(10);

/// Slave 1 answered a read of `count` holding registers from `first` with `values`, at `at`.
fn holding(shadow: &Shadow, first: u16, values: &[u16], at: Instant) {
    let count = u16::try_from(values.len()).unwrap();
    let [a, b] = first.to_be_bytes();
    let [c, d] = count.to_be_bytes();
    let request = [0x03, a, b, c, d];
    let mut reply = vec![0x03, u8::try_from(values.len() * 2).unwrap()];
    for v in values {
        reply.extend_from_slice(&v.to_be_bytes());
    }
    shadow.record(1, &request, &reply, (at, SystemTime::now()));
}

fn read(function: u8, first: u16, count: u16) -> Vec<u8> {
    let [a, b] = first.to_be_bytes();
    let [c, d] = count.to_be_bytes();
    vec![function, a, b, c, d]
}

#[test]
fn a_subset_of_a_block_seen_is_served_and_a_read_past_it_gets_0x0b() {
    let shadow = Shadow::new(MAX_AGE);
    let now = Instant::now();
    holding(&shadow, 0x3000, &[1, 2, 3, 4], now);
    assert_eq!(
        shadow.answer(1, &read(0x03, 0x3001, 2), now),
        Ok(vec![0x03, 4, 0, 2, 0, 3])
    );
    assert_eq!(
        shadow.answer(1, &read(0x03, 0x3002, 3), now),
        Err(RequestError::Unseen)
    );
    // Each table apart, and each slave apart.
    assert_eq!(
        shadow.answer(1, &read(0x04, 0x3000, 1), now),
        Err(RequestError::Unseen)
    );
    assert_eq!(
        shadow.answer(2, &read(0x03, 0x3000, 1), now),
        Err(RequestError::Unseen)
    );
}

#[test]
fn data_older_than_max_age_gets_0x0b_and_a_newer_block_replaces_what_it_covers() {
    let shadow = Shadow::new(MAX_AGE);
    let then = Instant::now();
    holding(&shadow, 0, &[7, 7, 7], then);
    holding(&shadow, 1, &[9], then + Duration::from_secs(5));
    let later = then + MAX_AGE + Duration::from_secs(1);
    // Register 1 is fresh, registers 0 and 2 too old: a read of all three is as old as the oldest.
    assert_eq!(
        shadow.answer(1, &read(0x03, 1, 1), later),
        Ok(vec![0x03, 2, 0, 9])
    );
    assert_eq!(
        shadow.answer(1, &read(0x03, 0, 3), later),
        Err(RequestError::Unseen)
    );
    assert_eq!(
        shadow.answer(1, &read(0x03, 0, 3), then + Duration::from_secs(6)),
        Ok(vec![0x03, 6, 0, 7, 0, 9, 0, 7])
    );
}

#[test]
fn anything_but_a_read_gets_0x01_and_a_bad_quantity_0x03() {
    let shadow = Shadow::new(MAX_AGE);
    let now = Instant::now();
    let write = [0x06, 0x00, 0x01, 0x00, 0x02];
    assert_eq!(
        shadow.answer(1, &write, now),
        Err(RequestError::ListenOnly(0x06))
    );
    let read_write = [0x17, 0, 0, 0, 1, 0, 0, 0, 1, 2, 0, 5];
    assert_eq!(
        shadow.answer(1, &read_write, now),
        Err(RequestError::ListenOnly(0x17))
    );
    assert_eq!(
        shadow.answer(1, &read(0x03, 0, 126), now),
        Err(RequestError::Unreadable(0x03))
    );
}

#[test]
fn coils_are_kept_bit_by_bit_and_served_packed() {
    let shadow = Shadow::new(MAX_AGE);
    let now = Instant::now();
    // Ten coils from 0013H: CD 01 (the spec's example).
    shadow.record(
        1,
        &read(0x01, 0x13, 10),
        &[0x01, 2, 0xCD, 0x01],
        (now, SystemTime::now()),
    );
    assert_eq!(
        shadow.answer(1, &read(0x01, 0x15, 3), now),
        Ok(vec![0x01, 1, 0b011])
    );
    assert_eq!(
        shadow.answer(1, &read(0x02, 0x13, 1), now),
        Err(RequestError::Unseen)
    );
}

#[test]
fn a_reply_that_does_not_carry_its_count_is_not_kept() {
    let shadow = Shadow::new(MAX_AGE);
    let now = Instant::now();
    shadow.record(
        1,
        &read(0x03, 0, 2),
        &[0x03, 2, 0, 1],
        (now, SystemTime::now()),
    );
    assert_eq!(
        shadow.answer(1, &read(0x03, 0, 1), now),
        Err(RequestError::Unseen)
    );
}

#[test]
fn a_slave_keeps_its_newest_blocks_only() {
    let shadow = Shadow::new(MAX_AGE);
    let now = Instant::now();
    let blocks = u16::try_from(MAX_BLOCKS).unwrap() + 10;
    for i in 0..blocks {
        holding(&shadow, i * 10, &[i], now);
    }
    assert_eq!(
        shadow.answer(1, &read(0x03, 0, 1), now),
        Err(RequestError::Unseen)
    );
    let last = (blocks - 1) * 10;
    assert_eq!(
        shadow.answer(1, &read(0x03, last, 1), now),
        Ok(vec![0x03, 2, 0, u8::try_from(blocks - 1).unwrap()])
    );
    assert_eq!(shadow.take_changed(), vec![1]);
    assert!(shadow.take_changed().is_empty());
}

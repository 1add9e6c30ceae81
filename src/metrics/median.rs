//! The median of a slave's recent round trips, for the status page.

use std::time::Duration;

/// The median of `samples`, `None` if there are none.
pub(crate) fn median(samples: impl IntoIterator<Item = Duration>) -> Option<Duration> {
    let mut samples: Vec<Duration> = samples.into_iter().collect();
    if samples.is_empty() {
        return None;
    }
    samples.sort_unstable();
    let middle = samples.len() / 2;
    Some(if samples.len() % 2 == 1 {
        samples[middle]
    } else {
        (samples[middle - 1] + samples[middle]) / 2
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_median_of_an_odd_and_an_even_count_and_of_none() {
        let ms = Duration::from_millis;
        assert_eq!(median([ms(30), ms(10), ms(20)]), Some(ms(20)));
        assert_eq!(median([ms(40), ms(10), ms(20), ms(30)]), Some(ms(25)));
        assert_eq!(median([]), None);
    }
}

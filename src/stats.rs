//! Order statistics shared by the stages and the evaluation: the median, one definition.

use std::cmp::Ordering;

/// A value with a total order (`f32`, `f64`: IEEE's totalOrder, NaN last).
pub trait TotalOrder: Copy {
    fn total_order(&self, other: &Self) -> Ordering;
}

impl TotalOrder for f32 {
    fn total_order(&self, other: &Self) -> Ordering {
        self.total_cmp(other)
    }
}

impl TotalOrder for f64 {
    fn total_order(&self, other: &Self) -> Ordering {
        self.total_cmp(other)
    }
}

/// The upper median: the element at index `len / 2` of `values` in sorted order (for an even
/// count the higher of the two middle ones, no averaging, so it is always one of the values);
/// `None` when there are none. Reorders `values` (a partial sort, O(n)).
pub fn median<T: TotalOrder>(values: &mut [T]) -> Option<T> {
    if values.is_empty() {
        return None;
    }
    let m = values.len() / 2;
    Some(*values.select_nth_unstable_by(m, T::total_order).1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_median_is_the_upper_middle_value_of_the_sorted_order() {
        assert_eq!(median::<f32>(&mut []), None);
        assert_eq!(median(&mut [3.0f32]), Some(3.0));
        assert_eq!(median(&mut [4.0f32, 1.0, 3.0, 2.0]), Some(3.0));
        assert_eq!(median(&mut [5.0f64, -1.0, 2.0]), Some(2.0));
        // NaN sorts last, so it is the median only when most values are NaN.
        assert_eq!(median(&mut [f64::NAN, 1.0, 0.0]), Some(1.0));
        // Against sorting, on values with ties.
        let v: Vec<f64> = (0..101).map(|i| ((i * 37) % 11) as f64).collect();
        let mut sorted = v.clone();
        sorted.sort_by(f64::total_cmp);
        assert_eq!(median(&mut v.clone()), Some(sorted[50]));
    }
}

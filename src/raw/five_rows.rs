//! The five rows a 5 x 5 window reads around a row that moves down one at a time: what the
//! full-resolution demosaic keeps of per-row work (site fits, their logs, log chroma) instead
//! of whole-image planes of it.

/// Rows `y - 2 ..= y + 2` of something computed a row at a time, each computed once, when
/// first asked for, into the slot of its row number modulo five. A window mirrored at the top
/// and bottom borders reads only rows within two of its own, so it finds them all here.
pub(super) struct FiveRows<T> {
    rows: [T; 5],
    /// The first row not computed yet.
    next: usize,
}

impl<T: Default> FiveRows<T> {
    /// Nothing computed yet; the first row to compute is `first`.
    pub(super) fn starting_at(first: usize) -> Self {
        FiveRows {
            rows: Default::default(),
            next: first,
        }
    }
}

impl<T> FiveRows<T> {
    /// Computes every row not computed yet below `end`, in order: `compute(k, slot)` writes
    /// row k into its slot (which held row k - 5).
    pub(super) fn compute_to(&mut self, end: usize, mut compute: impl FnMut(usize, &mut T)) {
        for k in self.next..end {
            compute(k, &mut self.rows[k % 5]);
        }
        self.next = self.next.max(end);
    }

    /// Row `k`, one of the last five computed.
    pub(super) fn row(&self, k: usize) -> &T {
        &self.rows[k % 5]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_row_is_computed_once_and_kept_while_it_is_within_two_rows() {
        let mut rows = FiveRows::<usize>::starting_at(3);
        let mut computed = Vec::new();
        for y in 5..20 {
            rows.compute_to(y + 3, |k, slot| {
                computed.push(k);
                *slot = k;
            });
            for k in y - 2..=y + 2 {
                assert_eq!(*rows.row(k), k, "row {k} at {y}");
            }
        }
        // Asking for fewer rows than already computed computes nothing.
        rows.compute_to(10, |_, _| panic!("computed again"));
        assert_eq!(computed, (3..22).collect::<Vec<_>>());
    }
}

//! Deterministic K-light subsets of a light set, spread over the hemisphere: what a scanner
//! with few LEDs sees of a benchmark captured under many.

/// Indices (ascending) of `k` of `directions`, chosen by greedy farthest-point sampling:
/// the most frontal light (largest z) first, then each time the light whose smallest angle to
/// the lights already chosen is largest. Ties go to the lower index, so the subset depends on
/// the directions alone. `k` at or above the count returns every light.
pub fn farthest_point(directions: &[[f64; 3]], k: usize) -> Vec<usize> {
    let n = directions.len();
    if k >= n {
        return (0..n).collect();
    }
    let unit: Vec<[f64; 3]> = directions.iter().map(|d| normalised(*d)).collect();
    let mut chosen = Vec::with_capacity(k);
    // Largest cosine to any chosen light (= smallest angle), per light.
    let mut nearest_cos = vec![f64::NEG_INFINITY; n];
    let first = (0..n).fold(
        0,
        |best, i| if unit[i][2] > unit[best][2] { i } else { best },
    );
    let mut next = first;
    while chosen.len() < k {
        chosen.push(next);
        for (i, u) in unit.iter().enumerate() {
            nearest_cos[i] = nearest_cos[i].max(dot(u, &unit[next]));
        }
        let mut best = None::<usize>;
        for (i, &cos) in nearest_cos.iter().enumerate() {
            if chosen.contains(&i) {
                continue;
            }
            if best.map_or(true, |b| cos < nearest_cos[b]) {
                best = Some(i);
            }
        }
        match best {
            Some(b) => next = b,
            None => break,
        }
    }
    chosen.sort_unstable();
    chosen
}

fn normalised(d: [f64; 3]) -> [f64; 3] {
    let norm = dot(&d, &d).sqrt();
    d.map(|v| v / norm)
}

fn dot(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn starts_frontal_and_spreads_over_the_ring() {
        // A frontal light and eight on a 45 degree ring, plus a near-duplicate of ring light 1.
        use std::f64::consts::FRAC_1_SQRT_2 as H;
        let mut dirs = vec![[0.05, 0.0, 0.99]];
        for j in 0..8 {
            let a = j as f64 * std::f64::consts::FRAC_PI_4;
            dirs.push([a.cos() * H, a.sin() * H, H]);
        }
        dirs.push([0.70, 0.02, H]);
        // Frontal first, then the ring: the four lights 90 degrees apart come before the rest.
        assert_eq!(farthest_point(&dirs, 1), vec![0]);
        let five = farthest_point(&dirs, 5);
        assert_eq!(five.len(), 5);
        assert!(five.contains(&0));
        let ring: Vec<usize> = five.iter().copied().filter(|&i| i != 0).collect();
        for pair in ring.windows(2) {
            assert_eq!(
                (pair[1] - pair[0]) % 2,
                0,
                "{five:?} is not every other ring light"
            );
        }
        // The near-duplicate is the last light chosen.
        assert!(!farthest_point(&dirs, 9).contains(&9));
        assert_eq!(farthest_point(&dirs, 20).len(), 10);
    }
}

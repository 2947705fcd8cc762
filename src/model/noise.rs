//! Each subsystem's own noise variances (`fit`, docs/theory.md §16).

use std::collections::HashMap;

use super::{Model, Params};

impl Model {
    /// The same model with the diagonal of `key` (`"Q"` or `"M"`) of subsystem `i` (0-based)
    /// at `values[i·d .. (i+1)·d]` at every step (`d = n` or `q`), the off-diagonal entries
    /// as configured. Subsystems that shared a parameter set share it still where their
    /// values agree.
    pub fn with_diagonals_per_subsystem(&self, key: &str, values: &[f64]) -> Model {
        let d = self.params[0].get(key).nrows();
        debug_assert_eq!(values.len(), self.subsystems * d);
        let mut sets: Vec<Params> = Vec::new();
        let mut made: HashMap<(u32, Vec<u64>), u32> = HashMap::new();
        let mut windows = self.windows.clone();
        for window in &mut windows {
            for (i, id) in window.ids.iter_mut().enumerate() {
                let own = &values[i * d..(i + 1) * d];
                let bits = own.iter().map(|v| v.to_bits()).collect();
                *id = *made.entry((*id, bits)).or_insert_with(|| {
                    let mut set = self.params[*id as usize].clone();
                    let matrix = set.get_mut(key);
                    for (k, &v) in own.iter().enumerate() {
                        matrix[(k, k)] = v;
                    }
                    sets.push(set);
                    (sets.len() - 1) as u32
                });
            }
        }
        let mut model = self.clone();
        model.params = sets;
        model.windows = windows;
        model
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_subsystem_gets_its_own_diagonal_and_equal_ones_share_a_set() {
        let text = "subsystems = 3\n[interconnection]\nplus = 1\nminus = 0\n[model]\nA = [[0.5, 0.1], [0.0, 0.4]]\nB = [[0.0], [0.0]]\nD = [[0.0, 0.0]]\nJ = [[1.0, 0.0]]\nM = 0.1\nQ = [[1.0, 0.2], [0.2, 2.0]]\n[dropout]\np = 0.9\n[initial]\nmean = [0.0, 0.0]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n";
        let model = Model::from_toml_str("t", std::path::Path::new("."), text).unwrap();
        let values = [3.0, 4.0, 3.0, 4.0, 5.0, 6.0];
        let fitted = model.with_diagonals_per_subsystem("Q", &values);
        for i in 0..3 {
            let q = &fitted.params(1, i + 1).Q;
            assert_eq!((q[(0, 0)], q[(1, 1)]), (values[2 * i], values[2 * i + 1]));
            assert_eq!((q[(0, 1)], q[(1, 0)]), (0.2, 0.2));
            assert_eq!(fitted.params(1, i + 1).A, model.params(1, 1).A);
        }
        assert_eq!(fitted.param_sets().len(), 2);
    }
}

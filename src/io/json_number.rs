//! Numbers that must come back from JSON bit for bit, the sums of a Monte Carlo part included
//! when a filter overflowed: JSON has no infinity or NaN, so those are written as the strings
//! `"inf"`, `"-inf"` and `"NaN"`, finite ones as numbers (the shortest form that reads back
//! exactly; the crate parses JSON with serde_json's `float_roundtrip`). Use as
//! `#[serde(with = "crate::io::json_number::one")]`, or `many` for a `Vec<f64>`.

use serde::{Deserialize, Deserializer, Serialize, Serializer, de::Error as _};

/// One number, as JSON holds it.
#[derive(Serialize, Deserialize)]
#[serde(untagged)]
enum Repr {
    Number(f64),
    Text(String),
}

impl From<f64> for Repr {
    fn from(v: f64) -> Self {
        if v.is_finite() {
            Repr::Number(v)
        } else {
            Repr::Text(v.to_string())
        }
    }
}

impl Repr {
    fn value<E: serde::de::Error>(self) -> Result<f64, E> {
        match self {
            Repr::Number(v) => Ok(v),
            Repr::Text(s) => match s.as_str() {
                "inf" | "-inf" | "NaN" => Ok(s.parse().expect("Rust reads what it writes")),
                _ => Err(E::custom(format!(
                    "expected a number, \"inf\", \"-inf\" or \"NaN\", found \"{}\"",
                    crate::messages::excerpt(&s)
                ))),
            },
        }
    }
}

/// `#[serde(with)]` for an `f64`.
pub mod one {
    use super::*;

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        Repr::from(*v).serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Repr::deserialize(d)?.value()
    }
}

/// `#[serde(with)]` for a `Vec<f64>`.
pub mod many {
    use super::*;

    pub fn serialize<S: Serializer>(v: &[f64], s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(v.iter().map(|&x| Repr::from(x)))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f64>, D::Error> {
        Vec::<Repr>::deserialize(d)?
            .into_iter()
            .map(|r| r.value().map_err(D::Error::custom::<D::Error>))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    #[derive(Debug, serde::Serialize, serde::Deserialize)]
    struct Sums {
        #[serde(with = "super::one")]
        one: f64,
        #[serde(with = "super::many")]
        many: Vec<f64>,
    }

    /// Every value, the awkward ones included, reads back with the same bits.
    #[test]
    fn numbers_come_back_bit_for_bit() {
        let values = vec![
            0.1 + 0.2,
            -0.0,
            f64::MIN_POSITIVE / 3.0,
            f64::MAX,
            1.0 / 3.0,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            2.225_073_858_507_201e-308,
            9_007_199_254_740_993.0,
        ];
        for &v in &values {
            let text = serde_json::to_string(&Sums {
                one: v,
                many: values.clone(),
            })
            .unwrap();
            let back: Sums = serde_json::from_str(&text).unwrap();
            assert_eq!(back.one.to_bits(), v.to_bits(), "{text}");
            let bits = |x: &[f64]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&back.many), bits(&values), "{text}");
        }
        let bad = serde_json::from_str::<Sums>(r#"{"one": "lots", "many": []}"#);
        assert!(bad.unwrap_err().to_string().contains("found \"lots\""));
    }
}

//! The library's named options ([`Choice`]) as clap values: the names and their help come
//! from the library's table, so `--help` lists exactly what the library accepts.

use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser};
use sisfilt::choice::Choice;

/// The parser of an option whose value is one of `T`'s names.
pub fn choice<T: Choice>() -> impl TypedValueParser<Value = T> {
    PossibleValuesParser::new(T::VARIANTS.iter().map(|v| {
        let value = PossibleValue::new(v.name);
        if v.help.is_empty() {
            value
        } else {
            value.help(v.help)
        }
    }))
    .try_map(|name| T::from_name(&name).ok_or("not one of the listed values"))
}

//! Closed sets of named options (a filter, a solver, an output format): each value's name,
//! as written on the command line and in JSON, and a sentence on what it means. The command
//! line offers them from this table, so the library needs no command-line crate.

/// One value of a [`Choice`]: its name and its meaning (empty when the name says it all).
#[derive(Debug, Clone, Copy)]
pub struct Variant<T> {
    pub value: T,
    pub name: &'static str,
    pub help: &'static str,
}

/// An enum whose values are offered by name (docs/theory.md §13).
pub trait Choice: Copy + PartialEq + Send + Sync + 'static {
    /// Every value, in the order they are offered.
    const VARIANTS: &'static [Variant<Self>];

    /// The value's entry in [`Choice::VARIANTS`].
    fn variant(self) -> Option<&'static Variant<Self>> {
        Self::VARIANTS.iter().find(|v| v.value == self)
    }

    /// The value's name (the same as its serialized form).
    fn name(self) -> &'static str {
        self.variant().map_or("", |v| v.name)
    }

    /// What the value means.
    fn help(self) -> &'static str {
        self.variant().map_or("", |v| v.help)
    }

    /// The value called `name`, if any.
    fn from_name(name: &str) -> Option<Self> {
        Self::VARIANTS
            .iter()
            .find(|v| v.name == name)
            .map(|v| v.value)
    }
}

#[cfg(test)]
mod tests {
    use super::Choice;
    use crate::filter::{Dropouts, FilterKind, InterconnectFrom, SecondMoment};
    use crate::interconnect::SolverKind;
    use crate::io::estimates::Format;

    /// Each value has one name, the one JSON files carry, and the name leads back to it.
    fn names_are_the_serialized_forms<T: Choice + serde::Serialize + std::fmt::Debug>() {
        for v in T::VARIANTS {
            assert_eq!(
                serde_json::to_value(v.value).unwrap(),
                v.name,
                "{:?}",
                v.value
            );
            assert_eq!(v.value.name(), v.name);
            assert_eq!(T::from_name(v.name), Some(v.value));
        }
        let names: std::collections::BTreeSet<_> = T::VARIANTS.iter().map(|v| v.name).collect();
        assert_eq!(names.len(), T::VARIANTS.len(), "a name is listed twice");
        assert_eq!(T::from_name("no-such-value"), None);
    }

    #[test]
    fn every_choice_names_its_values_as_json_does() {
        names_are_the_serialized_forms::<FilterKind>();
        names_are_the_serialized_forms::<SolverKind>();
        names_are_the_serialized_forms::<SecondMoment>();
        names_are_the_serialized_forms::<InterconnectFrom>();
        names_are_the_serialized_forms::<Dropouts>();
        names_are_the_serialized_forms::<Format>();
        names_are_the_serialized_forms::<crate::evaluate::Compared>();
    }
}

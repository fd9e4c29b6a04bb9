//! Who may see what of the store (docs/portal.md, "Who sees what"). A
//! researcher's uploads, robot files (sets), experiments and results are
//! hers: other users see none of it, admins see everything. An upload its
//! owner shared with the lab ([`Visibility::Lab`]) every user may see and
//! run, read-only. What the robot's own people made (admins, developers,
//! operators, the host itself: `boot`, `dev`, `lab`, `robot:NAME`) is the
//! robot's: every user sees its record; a researcher gets its bytes and
//! text only where the owner's lab kit setting lets them leave the robot
//! (`kit`).
//!
//! Invariant: one predicate per kind of thing, used by every route, archive
//! and listing that hands it out.

use std::collections::BTreeSet;

pub use super::records::Visibility;
use super::records::{ComponentRecord, SetRecord};
use super::users::{Principal, Role, User};

/// The store's owners as access sees them: which of them are researchers.
#[derive(Clone, Debug, Default)]
pub struct Access {
    researchers: BTreeSet<String>,
    /// The owner lets the robot's own bytes and text (the baseline's robot
    /// file and components) leave the robot for researchers (the lab kit).
    kit: bool,
}

impl Access {
    /// Access among `users`, with the owner's lab kit setting `kit`.
    pub fn new(users: &[User], kit: bool) -> Access {
        let researchers = users.iter().filter(|u| u.role == Role::Researcher).map(|u| u.name.clone()).collect();
        Access { researchers, kit }
    }

    /// Whether what `owner` made is a researcher's (hers alone).
    pub fn is_researchers(&self, owner: &str) -> bool {
        // A lab's experiment on a robot is imported as `USER@LAB`: the
        // lab's researcher's, never the robot's.
        self.researchers.contains(owner) || owner.contains('@')
    }

    /// Whether `reader` may see the record of something `owner` made:
    /// their own, the robot's, or anything for an admin.
    pub fn may_see(&self, reader: &Principal, owner: &str) -> bool {
        reader.role == Role::Admin || reader.name == owner || !self.is_researchers(owner)
    }

    /// Whether `reader` may have the bytes or text of something `owner`
    /// made: their own, anything for an admin, and the robot's for anyone
    /// but a researcher, for her while the kit lets it leave the robot.
    pub fn may_read(&self, reader: &Principal, owner: &str) -> bool {
        reader.role == Role::Admin
            || reader.name == owner
            || (!self.is_researchers(owner) && (reader.role != Role::Researcher || self.kit))
    }

    /// Whether `reader` may see upload `record` (and run it by name).
    pub fn may_see_component(&self, reader: &Principal, record: &ComponentRecord) -> bool {
        record.visibility == Visibility::Lab || self.may_see(reader, &record.uploaded_by)
    }

    /// Whether `reader` may have upload `record`'s bytes.
    pub fn may_read_component(&self, reader: &Principal, record: &ComponentRecord) -> bool {
        record.visibility == Visibility::Lab || self.may_read(reader, &record.uploaded_by)
    }

    /// Whether `reader` may see set `set`'s record.
    pub fn may_see_set(&self, reader: &Principal, set: &SetRecord) -> bool {
        self.may_see(reader, &set.created_by)
    }

    /// Whether `reader` may have set `set`'s robot file.
    pub fn may_read_set(&self, reader: &Principal, set: &SetRecord) -> bool {
        self.may_read(reader, &set.created_by)
    }
}

#[cfg(test)]
mod tests {
    use super::{Access, Principal, Role, User};

    fn user(name: &str, role: Role) -> User {
        User {
            principal: Principal { name: name.into(), role, platforms: vec!["control".into()] },
            hash: String::new(),
        }
    }

    #[test]
    fn who_sees_and_reads_whose_things() {
        let users = [
            user("ana", Role::Researcher),
            user("ben", Role::Researcher),
            user("dev", Role::Developer),
            user("boss", Role::Admin),
            user("olga", Role::Operator),
        ];
        // (reader, owner, kit) -> (sees, reads)
        let cases = [
            ("ana", "ana", false, (true, true)),
            ("ana", "ben", false, (false, false)),
            ("ana", "ben", true, (false, false)),
            ("ana", "boot", false, (true, false)),
            ("ana", "boot", true, (true, true)),
            ("ana", "dev", true, (true, true)),
            ("ana", "bob@lab1", true, (false, false)),
            ("dev", "ana", true, (false, false)),
            ("dev", "boot", false, (true, true)),
            ("dev", "dev", false, (true, true)),
            ("olga", "ana", false, (false, false)),
            ("olga", "boss", false, (true, true)),
            ("boss", "ana", false, (true, true)),
            ("boss", "bob@lab1", false, (true, true)),
        ];
        for (reader, owner, kit, expected) in cases {
            let access = Access::new(&users, kit);
            let reader_user = users.iter().find(|u| u.name == reader).unwrap();
            let got = (access.may_see(reader_user, owner), access.may_read(reader_user, owner));
            assert_eq!(got, expected, "{reader} of {owner}'s, kit {kit}");
        }
    }
}

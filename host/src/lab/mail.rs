//! A user's own mail subscription (docs/lab.md, "People are told"): where
//! the lab mails her and for which events of her own experiments. Kept by
//! `notify`; this file is the use case, audited.

use super::{Lab, LabError};
use crate::notify::NotifyError;
use crate::notify::mail::Subscription;
use crate::store::users::Principal;

impl Lab {
    /// `user`'s mail subscription, if any.
    pub fn mail_subscription(&self, user: &Principal) -> Result<Option<Subscription>, LabError> {
        self.mailing()?.subscription(&user.name).map_err(mail_error)
    }

    /// Sets (or with `None`, ends) `user`'s own mail subscription.
    pub fn set_mail_subscription(
        &self,
        user: &Principal,
        subscription: Option<Subscription>,
    ) -> Result<Option<Subscription>, LabError> {
        let target = format!("mail of {}", user.name);
        self.audited(
            &user.name,
            "mail-subscription",
            &target,
            || {
                self.mailing()?.subscribe(&user.name, subscription.clone()).map_err(mail_error)?;
                Ok(subscription.clone())
            },
            |s| match s {
                Some(s) => format!("{} event kinds to {}", s.events.len(), s.address),
                None => "no mail".into(),
            },
        )
    }

    fn mailing(&self) -> Result<&crate::notify::Notifier, LabError> {
        match &self.notifier {
            Some(notifier) if notifier.mails() => Ok(notifier),
            _ => Err(LabError::Conflict(format!(
                "this lab sends no mail: its owner has not configured {} beside the store",
                crate::notify::mail::MAIL_FILE
            ))),
        }
    }
}

fn mail_error(e: NotifyError) -> LabError {
    match e {
        NotifyError::Mail(crate::notify::mail::MailError::Subscription(m)) => LabError::BadRequest(m),
        other => LabError::Host(other.to_string()),
    }
}

//! One error type for the library. Every error that comes from user input names the file, the
//! field and what was expected, so the CLI can print it as one line and exit with code 2.

use std::path::{Path, PathBuf};

/// Errors raised by LightFuse. [`Error::is_user_error`] tells the CLI which exit code to use.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file could not be opened, read or written.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A file was read but its content is not what LightFuse expects.
    #[error("{}: {field}: {message}", file.display())]
    Invalid {
        file: PathBuf,
        field: String,
        message: String,
    },
    /// A command-line argument or combination of arguments is wrong.
    #[error("{0}")]
    Usage(String),
    /// A library LightFuse calls failed at run time on valid input (e.g. Open Image Denoise
    /// could not create its device): not the user's input, so exit code 1.
    #[error("{library} failed: {message}")]
    External {
        library: &'static str,
        message: String,
    },
}

impl Error {
    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.as_ref().to_path_buf(),
            source,
        }
    }

    pub fn invalid(
        file: impl AsRef<Path>,
        field: impl Into<String>,
        message: impl Into<String>,
    ) -> Self {
        Error::Invalid {
            file: file.as_ref().to_path_buf(),
            field: field.into(),
            message: message.into(),
        }
    }

    /// True when the error is the user's input (exit code 2), false for internal failures.
    pub fn is_user_error(&self) -> bool {
        match self {
            Error::Invalid { .. } | Error::Usage(_) => true,
            Error::External { .. } => false,
            Error::Io { source, .. } => matches!(
                source.kind(),
                std::io::ErrorKind::NotFound
                    | std::io::ErrorKind::PermissionDenied
                    | std::io::ErrorKind::UnexpectedEof
                    | std::io::ErrorKind::InvalidData
                    | std::io::ErrorKind::IsADirectory
            ),
        }
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failing_library_is_not_the_users_error() {
        let e = Error::External {
            library: "Open Image Denoise",
            message: "no device".into(),
        };
        assert!(!e.is_user_error());
        assert_eq!(e.to_string(), "Open Image Denoise failed: no device");
        assert!(Error::Usage("x".into()).is_user_error());
    }
}

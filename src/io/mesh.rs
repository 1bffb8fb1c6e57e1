//! Ordinary glTF mesh scenes (input of `surfelize`) — helper in progress.

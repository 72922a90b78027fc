//! Locks, and the one policy for a poisoned one.
//!
//! A lock is poisoned when a thread panicked while holding it. The daemon's critical sections
//! change their data in single steps that leave it whole (an `Arc` swapped, an entry pushed or
//! removed, a counter moved, an `Option` taken or set), so a panic between steps cannot leave
//! it half-changed; what a poisoned lock holds is as sound as before the panic. A panic is
//! itself a bug, reported where it happened (the request that hit it fails); refusing every
//! later request over it would turn one failed request into a daemon that serves nothing. So
//! every lock of the daemon is taken through these functions, which take the data whether or
//! not the lock is poisoned. The core's few locks (caches of CRSs and planes) follow the same
//! rule inline.

use std::sync::{Mutex, MutexGuard, PoisonError, RwLock, RwLockReadGuard, RwLockWriteGuard};

/// Locks `m`, poisoned or not (see the module's policy).
pub fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Takes `l` to read, poisoned or not (see the module's policy).
pub fn read<T>(l: &RwLock<T>) -> RwLockReadGuard<'_, T> {
    l.read().unwrap_or_else(PoisonError::into_inner)
}

/// Takes `l` to write, poisoned or not (see the module's policy).
pub fn write<T>(l: &RwLock<T>) -> RwLockWriteGuard<'_, T> {
    l.write().unwrap_or_else(PoisonError::into_inner)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lock_poisoned_by_a_panic_still_gives_its_data() {
        let m = std::sync::Arc::new(Mutex::new(vec![1]));
        let m2 = m.clone();
        let _ = std::thread::spawn(move || {
            let mut g = m2.lock().unwrap();
            g.push(2);
            panic!("a bug while holding the lock");
        })
        .join();
        assert!(m.is_poisoned());
        assert_eq!(*lock(&m), vec![1, 2]);
    }
}

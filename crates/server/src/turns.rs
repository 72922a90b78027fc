//! The turns to run requests (`limits.max_running_requests`), shared by both ports and handed
//! round the clients fairly.
//!
//! A first-come queue lets one client that asks for many distinct tiles at once take every
//! turn while others wait behind its whole backlog: eight browsers' worth of tile requests
//! kept a one-point `sample` waiting 30 s. So a turn that comes free goes to the waiting
//! request whose client address holds the fewest turns now, then whose connection has started
//! the fewest requests so far (a new client before one that has been served a thousand
//! tiles), and only then to the one that came first: least attained service, as fair queueing
//! schedulers do it, so that a client asking much is slowed and one asking little is not.

use super::conns::Conn;
use patchwork_core::sync::lock;
use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::{Arc, Mutex};
use tokio::sync::oneshot;

/// The turns, and who waits for one.
pub struct Turns {
    total: usize,
    state: Mutex<State>,
}

#[derive(Default)]
struct State {
    free: usize,
    /// Turns held by each client address.
    held: HashMap<IpAddr, usize>,
    waiting: Vec<Waiter>,
    next: u64,
}

struct Waiter {
    seq: u64,
    client: Option<Arc<Conn>>,
    tx: oneshot::Sender<Turn>,
}

/// A turn to run: given back when dropped, to the next waiter in fair order.
pub struct Turn {
    turns: Arc<Turns>,
    ip: Option<IpAddr>,
    /// False once given back by hand (see [`Turns::hand_out`]).
    armed: bool,
}

impl Drop for Turn {
    fn drop(&mut self) {
        if self.armed {
            let mut s = lock(&self.turns.state);
            release(&mut s, self.ip);
            self.turns.hand_out(&mut s);
        }
    }
}

fn release(s: &mut State, ip: Option<IpAddr>) {
    s.free += 1;
    if let Some(ip) = ip {
        if let Some(n) = s.held.get_mut(&ip) {
            *n -= 1;
            if *n == 0 {
                s.held.remove(&ip);
            }
        }
    }
}

impl Turns {
    /// `total` turns, all free.
    pub fn new(total: usize) -> Arc<Turns> {
        Arc::new(Turns {
            total,
            state: Mutex::new(State {
                free: total,
                ..State::default()
            }),
        })
    }

    /// How many turns are taken now.
    pub fn taken(&self) -> usize {
        self.total - lock(&self.state).free
    }

    /// A turn for a request from `client` (None: not from a connection), once one is free and
    /// no waiter comes before it. Dropping the future leaves the queue.
    pub async fn take(self: &Arc<Self>, client: Option<Arc<Conn>>) -> Turn {
        let mut rx = {
            let mut s = lock(&self.state);
            if s.free > 0 && s.waiting.is_empty() {
                return self.grant(&mut s, client.as_ref());
            }
            let (tx, rx) = oneshot::channel();
            let seq = s.next;
            s.next += 1;
            s.waiting.push(Waiter { seq, client, tx });
            rx
        };
        loop {
            match (&mut rx).await {
                Ok(turn) => return turn,
                // Senders are dropped only with a turn sent, or by `hand_out` on a closed
                // receiver; neither leaves this one without its turn. Should it happen all the
                // same, wait again rather than run without a turn.
                Err(_) => {
                    let (tx, again) = oneshot::channel();
                    let mut s = lock(&self.state);
                    let seq = s.next;
                    s.next += 1;
                    s.waiting.push(Waiter {
                        seq,
                        client: None,
                        tx,
                    });
                    drop(s);
                    rx = again;
                }
            }
        }
    }

    fn grant(self: &Arc<Self>, s: &mut State, client: Option<&Arc<Conn>>) -> Turn {
        s.free -= 1;
        let ip = client.map(|c| c.peer.ip());
        if let Some(ip) = ip {
            *s.held.entry(ip).or_default() += 1;
        }
        Turn {
            turns: self.clone(),
            ip,
            armed: true,
        }
    }

    /// Gives the free turns to the waiters, fairest first (see the module's comment).
    fn hand_out(self: &Arc<Self>, s: &mut State) {
        s.waiting.retain(|w| !w.tx.is_closed());
        while s.free > 0 && !s.waiting.is_empty() {
            let rank = |w: &Waiter| {
                let held = w
                    .client
                    .as_ref()
                    .and_then(|c| s.held.get(&c.peer.ip()))
                    .copied()
                    .unwrap_or(0);
                let served = w.client.as_ref().map_or(0, |c| c.served());
                (held, served, w.seq)
            };
            let best = (0..s.waiting.len())
                .min_by_key(|&k| rank(&s.waiting[k]))
                .expect("not empty");
            let w = s.waiting.swap_remove(best);
            let turn = self.grant(s, w.client.as_ref());
            if let Err(mut back) = w.tx.send(turn) {
                // The waiter left meanwhile: the turn is free again, given back here, under
                // the lock its drop would take.
                back.armed = false;
                release(s, back.ip);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_freed_turn_goes_to_the_waiter_that_came_first_when_none_is_favoured() {
        let t = Turns::new(1);
        let first = t.take(None).await;
        assert_eq!(t.taken(), 1);
        let (a, b) = (t.clone(), t.clone());
        let wa = tokio::spawn(async move { a.take(None).await });
        tokio::task::yield_now().await;
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        let wb = tokio::spawn(async move { b.take(None).await });
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        drop(first);
        let ta = wa.await.unwrap();
        assert!(!wb.is_finished());
        drop(ta);
        let tb = wb.await.unwrap();
        drop(tb);
        assert_eq!(t.taken(), 0);
    }

    #[tokio::test]
    async fn a_waiter_that_leaves_gives_its_turn_on() {
        let t = Turns::new(1);
        let first = t.take(None).await;
        let a = t.clone();
        let gone = tokio::spawn(async move { a.take(None).await });
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        gone.abort();
        let _ = gone.await;
        drop(first);
        let again = tokio::time::timeout(std::time::Duration::from_secs(5), t.take(None))
            .await
            .expect("the turn of a waiter that left is free");
        drop(again);
        assert_eq!(t.taken(), 0);
    }
}

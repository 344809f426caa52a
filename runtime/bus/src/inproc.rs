//! In-process transport: threads of one process, for unit tests of stages and of the bus
//! contracts. Bounded queues per subscriber; lossless topics make the publisher wait.

use std::collections::{HashMap, VecDeque};
use std::mem::MaybeUninit;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use gprflow_msg as msg;

use super::{BusError, FillFn, Frame, FrameData, FrameHeader, Publisher, Result, Subscriber, TopicConfig, Transport};

const POLL: Duration = Duration::from_millis(20);

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// A subscriber's queue and whether the subscriber is still attached (cleared on drop,
/// under the same lock, so a publisher knows exactly which frames reached a live subscriber).
struct QueueState {
    frames: VecDeque<(FrameHeader, Arc<[u8]>)>,
    attached: bool,
}

struct Queue {
    frames: Mutex<QueueState>,
    /// Signalled on push (wakes the subscriber) and on pop (wakes a waiting publisher).
    changed: Condvar,
    capacity: usize,
}

#[derive(Default)]
struct TopicState {
    subscribers: Mutex<Vec<(u64, Arc<Queue>)>>,
    config: Mutex<Option<TopicConfig>>,
}

/// The in-process transport; clones share topics.
#[derive(Clone, Default)]
pub struct InProcess {
    topics: Arc<Mutex<HashMap<String, Arc<TopicState>>>>,
    next_id: Arc<Mutex<u64>>,
    stop: Arc<AtomicBool>,
}

impl std::fmt::Debug for InProcess {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("InProcess").finish_non_exhaustive()
    }
}

impl InProcess {
    /// A transport whose blocking sends give up when `stop` turns true.
    pub fn new(stop: Arc<AtomicBool>) -> Self {
        Self {
            stop,
            ..Self::default()
        }
    }

    fn topic(&self, config: &TopicConfig) -> Result<Arc<TopicState>> {
        let state = lock(&self.topics).entry(config.name.clone()).or_default().clone();
        let mut existing = lock(&state.config);
        match existing.as_ref() {
            Some(c) if c != config => {
                return Err(BusError::Transport {
                    topic: config.name.clone(),
                    what: format!("opened with different settings: {c:?} vs {config:?}"),
                });
            }
            Some(_) => {}
            None => *existing = Some(config.clone()),
        }
        drop(existing);
        Ok(state)
    }
}

impl Transport for InProcess {
    fn publisher(&self, topic: &TopicConfig) -> Result<Box<dyn Publisher>> {
        Ok(Box::new(InProcPub {
            topic: topic.name.clone(),
            latest_only: topic.latest_only,
            state: self.topic(topic)?,
            stop: self.stop.clone(),
        }))
    }

    fn subscriber(&self, topic: &TopicConfig) -> Result<Box<dyn Subscriber>> {
        let state = self.topic(topic)?;
        let queue = Arc::new(Queue {
            frames: Mutex::new(QueueState {
                frames: VecDeque::with_capacity(topic.buffer),
                attached: true,
            }),
            changed: Condvar::new(),
            capacity: topic.buffer,
        });
        let id = {
            let mut next = lock(&self.next_id);
            *next += 1;
            *next
        };
        lock(&state.subscribers).push((id, queue.clone()));
        Ok(Box::new(InProcSub {
            topic: topic.name.clone(),
            id,
            state,
            queue,
        }))
    }
}

struct InProcPub {
    topic: String,
    latest_only: bool,
    state: Arc<TopicState>,
    stop: Arc<AtomicBool>,
}

impl Publisher for InProcPub {
    fn topic(&self) -> &str {
        &self.topic
    }

    fn send_with(&mut self, header: FrameHeader, len: usize, fill: &mut FillFn<'_>) -> Result<usize> {
        let mut buf: Vec<MaybeUninit<u8>> = vec![MaybeUninit::uninit(); len];
        msg::fill_payload(&mut buf, fill).map_err(|source| BusError::Encode {
            topic: self.topic.clone(),
            source,
        })?;
        // SAFETY: `fill_payload` returned Ok: `fill` handed back the token of this very
        // buffer, which only a writer that wrote each of its bytes makes.
        let bytes: Vec<u8> = buf.into_iter().map(|b| unsafe { b.assume_init() }).collect();
        let payload: Arc<[u8]> = bytes.into();
        let queues: Vec<Arc<Queue>> = lock(&self.state.subscribers).iter().map(|(_, q)| q.clone()).collect();
        let mut reached = 0;
        for queue in &queues {
            let mut guard = lock(&queue.frames);
            loop {
                let QueueState { frames, attached } = &mut *guard;
                if !*attached {
                    break; // the subscriber left: not reached
                }
                if frames.len() < queue.capacity {
                    frames.push_back((header, payload.clone()));
                    reached += 1;
                    queue.changed.notify_all();
                    break;
                }
                if self.latest_only {
                    frames.pop_front();
                    continue;
                }
                if self.stop.load(Ordering::Relaxed) {
                    return Err(BusError::Shutdown);
                }
                guard = queue
                    .changed
                    .wait_timeout(guard, POLL)
                    .unwrap_or_else(PoisonError::into_inner)
                    .0;
            }
        }
        Ok(reached)
    }

    fn subscriber_count(&self) -> usize {
        lock(&self.state.subscribers).len()
    }
}

struct InProcSub {
    topic: String,
    id: u64,
    state: Arc<TopicState>,
    queue: Arc<Queue>,
}

impl Drop for InProcSub {
    fn drop(&mut self) {
        lock(&self.state.subscribers).retain(|(id, _)| *id != self.id);
        lock(&self.queue.frames).attached = false;
        self.queue.changed.notify_all();
    }
}

impl Subscriber for InProcSub {
    fn topic(&self) -> &str {
        &self.topic
    }

    fn try_receive(&mut self) -> Result<Option<Frame>> {
        let front = lock(&self.queue.frames).frames.pop_front();
        self.queue.changed.notify_all();
        Ok(front.map(|(header, payload)| Frame {
            header,
            data: if payload.is_empty() {
                FrameData::Empty
            } else {
                FrameData::Shared(payload)
            },
        }))
    }

    fn wait(&mut self, timeout: Duration) -> Result<()> {
        let frames = lock(&self.queue.frames);
        if frames.frames.is_empty() {
            let _ = self
                .queue
                .changed
                .wait_timeout(frames, timeout)
                .unwrap_or_else(PoisonError::into_inner);
        }
        Ok(())
    }
}

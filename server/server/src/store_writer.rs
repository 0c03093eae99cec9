//! The one place that writes episode rows: a task fed by the lifecycle's events (a call answered, an episode
//! ended) and by the server's own requests (a prepared episode's row, "catch up with this episode" before a read),
//! plus a periodic pass for what no event reports (an episode whose thread died). One writer means the row of an
//! episode is written in the order things happened, and readers (the API's GET handlers, the console) never write:
//! they wait until the writer has caught up ([`StoreWriter::sync`]).
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use libero_records::json::utc_now_iso;
use libero_episode::lifecycle::{EpisodeEvent, EventSink};
use libero_episode::{EpisodeState, EpisodeStatus, RunDir};
use tokio::sync::{mpsc, oneshot};

use crate::episodes::Episodes;
use crate::live::LiveHubs;
use libero_store::{EpisodeEnd, NewEpisode, Store};

/// How often open episodes are checked for changes no event reports.
const STORE_SYNC_PERIOD: Duration = Duration::from_secs(1);

enum Message {
    Event(EpisodeEvent),
    /// A prepared episode's row; its preparation fails when the row cannot be stored, so the answer goes back.
    Insert { new: Box<NewEpisode>, done: oneshot::Sender<anyhow::Result<()>> },
    /// Catch up with one episode (or all open ones), then say so.
    Sync { id: Option<String>, done: oneshot::Sender<()> },
}

/// The sending side, held by the [`App`](crate::App) and, as an [`EventSink`], by the lifecycle.
#[derive(Clone)]
pub struct StoreWriter {
    tx: mpsc::UnboundedSender<Message>,
}

/// The writer's queue until [`run`] takes it (the writer starts when the server starts serving).
pub struct Inbox(mpsc::UnboundedReceiver<Message>);

pub fn channel() -> (StoreWriter, Inbox) {
    let (tx, rx) = mpsc::unbounded_channel();
    (StoreWriter { tx }, Inbox(rx))
}

impl StoreWriter {
    /// The lifecycle's event sink: queues the event and returns at once (it is called on episode threads).
    pub fn events(&self) -> EventSink {
        let tx = self.tx.clone();
        Arc::new(move |event| {
            let _ = tx.send(Message::Event(event));
        })
    }

    /// Stores a prepared episode's row through the writer.
    pub async fn insert(&self, new: NewEpisode) -> anyhow::Result<()> {
        let (done, answer) = oneshot::channel();
        self.tx.send(Message::Insert { new: Box::new(new), done }).map_err(|_| anyhow::anyhow!("the store writer has stopped"))?;
        answer.await.map_err(|_| anyhow::anyhow!("the store writer stopped before storing the row"))?
    }

    /// Waits until the writer has written what `id` (all open episodes with `None`) shows now. Returns at once
    /// when the writer is not running.
    pub async fn sync(&self, id: Option<&str>) {
        let (done, written) = oneshot::channel();
        if self.tx.send(Message::Sync { id: id.map(str::to_owned), done }).is_ok() {
            let _ = written.await;
        }
    }
}

/// The writer task: runs until its queue closes or it is aborted (at the server's end, after a last
/// [`StoreWriter::sync`]).
pub async fn run(Inbox(mut inbox): Inbox, store: Store, episodes: Arc<Episodes>, hubs: Arc<LiveHubs>) {
    let mut writer =
        Writer { store, episodes, hubs, synced: HashMap::new(), progressed: HashMap::new(), reported: HashMap::new(), results: HashMap::new() };
    let mut tick = tokio::time::interval(STORE_SYNC_PERIOD);
    loop {
        tokio::select! {
            message = inbox.recv() => match message {
                Some(Message::Event(EpisodeEvent::Called { id, accepted_agent_steps, stages })) => {
                    writer.reported.insert(id.clone(), (accepted_agent_steps, stages));
                    writer.sync(&id).await;
                }
                Some(Message::Event(EpisodeEvent::Ended { id, result })) => {
                    if let Some(result) = result {
                        writer.results.insert(id.clone(), result);
                    }
                    writer.sync(&id).await;
                }
                Some(Message::Insert { new, done }) => {
                    let _ = done.send(writer.insert(&new).await);
                }
                Some(Message::Sync { id, done }) => {
                    match id {
                        Some(id) => writer.sync(&id).await,
                        None => writer.sync_all().await,
                    }
                    let _ = done.send(());
                }
                None => return,
            },
            _ = tick.tick() => writer.sync_all().await,
        }
    }
}

struct Writer {
    store: Store,
    episodes: Arc<Episodes>,
    hubs: Arc<LiveHubs>,
    /// The last state written per episode, so only transitions cost a write.
    synced: HashMap<String, EpisodeState>,
    /// The progress last written per open episode, so only changes cost a write.
    progressed: HashMap<String, (u64, Option<(usize, usize)>)>,
    /// The progress each open episode's last answered call reported ([`EpisodeEvent::Called`]).
    reported: HashMap<String, (u64, Option<(usize, usize)>)>,
    /// Results the lifecycle handed over with an episode's end, until written.
    results: HashMap<String, Box<libero_records::records::RunResult>>,
}

impl Writer {
    async fn insert(&mut self, new: &NewEpisode) -> anyhow::Result<()> {
        self.store.insert_prepared(new).await?;
        self.hubs.notify();
        Ok(())
    }

    /// Writes `id`'s transition (started, ended) if its state changed since the last write, and an open
    /// episode's progress.
    async fn sync(&mut self, id: &str) {
        let Some(status) = self.episodes.lifecycle().status(id) else { return };
        let previous = self.synced.get(id).copied();
        if previous != Some(status.state) {
            match self.write_transition(id, previous, &status).await {
                Ok(()) => {
                    self.synced.insert(id.to_owned(), status.state);
                    self.hubs.notify();
                }
                Err(e) => eprintln!("warning: {e:#}"),
            }
        }
        match status.state {
            EpisodeState::Active => self.sync_progress(id).await,
            EpisodeState::Finished | EpisodeState::Aborted => {
                self.progressed.remove(id);
                self.reported.remove(id);
            }
            EpisodeState::Prepared => {}
        }
    }

    /// Syncs every episode whose last stored state is not final.
    async fn sync_all(&mut self) {
        let open: Vec<String> = self
            .episodes
            .lifecycle().ids()
            .into_iter()
            .filter(|id| !matches!(self.synced.get(id), Some(EpisodeState::Finished | EpisodeState::Aborted)))
            .collect();
        for id in open {
            self.sync(&id).await;
        }
    }

    /// Writes an open episode's steps and stages when they changed, for dashboards elsewhere.
    async fn sync_progress(&mut self, id: &str) {
        let Some(&now) = self.reported.get(id) else { return };
        if self.progressed.get(id) == Some(&now) {
            return;
        }
        let stages = now.1.map(|(completed, required)| (completed as i64, required as i64));
        match self.store.record_progress(id, now.0 as i64, stages).await {
            Ok(()) => {
                self.progressed.insert(id.to_owned(), now);
            }
            Err(e) => eprintln!("warning: {e}"),
        }
    }

    async fn write_transition(&mut self, id: &str, previous: Option<EpisodeState>, status: &EpisodeStatus) -> anyhow::Result<()> {
        // The initial observation exists exactly when start_episode succeeded.
        if status.latest_observation_id.is_some() && previous != Some(EpisodeState::Active) {
            self.store.mark_started(id, &utc_now_iso()).await?;
        }
        if matches!(status.state, EpisodeState::Finished | EpisodeState::Aborted) {
            // The result the end's event carried; read from the run only for an end no event told (an episode
            // whose thread died).
            let end = match self.results.remove(id) {
                Some(result) => Some(EpisodeEnd::from_result(&result)),
                None => EpisodeEnd::from_run(&RunDir::new(self.episodes.lifecycle().runs_dir().join(id))),
            };
            if let Some(end) = end {
                self.store.record_end(id, &end).await?;
            }
        }
        Ok(())
    }
}

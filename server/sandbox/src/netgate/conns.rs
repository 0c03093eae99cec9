//! What every socket the gateway or a relay serves shares: a thread with a runtime of its own ([`Running`]), and
//! the connection cap under which a new connection takes the place of the one idle the longest ([`Conns`]).
use super::*;

/// A thread running a current-thread runtime that serves one listener until told to stop.
pub(super) struct Running {
    pub(super) stop: Option<oneshot::Sender<()>>,
    pub(super) thread: Option<std::thread::JoinHandle<()>>,
}

impl Running {
    pub(super) fn spawn<F, Fut>(name: &str, listener: StdUnixListener, serve: F) -> Result<Self, GatewayError>
    where
        F: FnOnce(UnixListener) -> Fut + Send + 'static,
        Fut: Future<Output = ()> + 'static,
    {
        listener.set_nonblocking(true)?;
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        let listener = {
            let _in_runtime = rt.enter();
            UnixListener::from_std(listener)?
        };
        let (stop, stopped) = oneshot::channel::<()>();
        let thread = std::thread::Builder::new().name(name.to_owned()).spawn(move || {
            rt.block_on(async move {
                tokio::select! {
                    _ = stopped => {}
                    () = serve(listener) => {}
                }
            });
            // Drops every task (their records are written as they drop), then waits a little for name lookups.
            rt.shutdown_timeout(STOP_GRACE);
        })?;
        Ok(Self { stop: Some(stop), thread: Some(thread) })
    }

    pub(super) fn stop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The connections a socket serves, by age, so that one over the cap can take an idle one's place instead of
/// waiting in the backlog behind the agent's own slow connections.
pub(super) struct Conns {
    pub(super) cap: usize,
    pub(super) epoch: Instant,
    pub(super) next_id: AtomicU64,
    pub(super) open: Mutex<BTreeMap<u64, Arc<Conn>>>,
}

/// One served connection.
pub(super) struct Conn {
    /// Requests and tunnels in progress; 0: the connection waits for a request head and may be closed to make
    /// room (the relay's connections never count any).
    pub(super) busy: AtomicU64,
    /// When a request began or ended, or bytes moved, in ms since [`Conns::epoch`].
    pub(super) active_ms: AtomicU64,
    pub(super) abort: OnceLock<tokio::task::AbortHandle>,
}

/// A connection's place among [`Conns`], given up when the last holder (its task, its tunnel) drops it.
pub(super) struct Slot {
    pub(super) conns: Arc<Conns>,
    pub(super) id: u64,
    pub(super) conn: Arc<Conn>,
}

impl Slot {
    pub(super) fn touch(&self) {
        self.conn.active_ms.store(self.conns.epoch.elapsed().as_millis() as u64, Ordering::Relaxed);
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        if let Ok(mut open) = self.conns.open.lock() {
            open.remove(&self.id);
        }
    }
}

impl Conns {
    /// A place for a new connection: free, or taken from the open connection idle the longest (closed now);
    /// None when every one is busy.
    pub(super) fn admit(self: &Arc<Self>) -> Option<Arc<Slot>> {
        let mut open = self.open.lock().ok()?;
        if open.len() >= self.cap {
            let victim = open
                .iter()
                .filter(|(_, c)| c.busy.load(Ordering::Relaxed) == 0 && c.abort.get().is_some())
                .min_by_key(|(id, c)| (c.active_ms.load(Ordering::Relaxed), **id))
                .map(|(id, _)| *id)?;
            if let Some(c) = open.remove(&victim)
                && let Some(a) = c.abort.get()
            {
                a.abort();
            }
        }
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let conn = Arc::new(Conn {
            busy: AtomicU64::new(0),
            active_ms: AtomicU64::new(self.epoch.elapsed().as_millis() as u64),
            abort: OnceLock::new(),
        });
        open.insert(id, conn.clone());
        Some(Arc::new(Slot { conns: self.clone(), id, conn }))
    }
}

/// Accepts without pause, each connection served by a task of its own: `handle` with a place among `cap`, or
/// `full` when every place is busy.
pub(super) async fn accept_loop<H, HF, F>(listener: UnixListener, cap: usize, handle: H, full: F)
where
    H: Fn(UnixStream, Arc<Slot>) -> HF,
    HF: Future<Output = ()> + Send + 'static,
    F: Fn(UnixStream),
{
    let conns = Arc::new(Conns { cap: cap.max(1), epoch: Instant::now(), next_id: AtomicU64::new(0), open: Mutex::new(BTreeMap::new()) });
    loop {
        match listener.accept().await {
            Ok((stream, _)) => match conns.admit() {
                Some(slot) => {
                    let conn = slot.conn.clone();
                    let task = tokio::spawn(handle(stream, slot));
                    let _ = conn.abort.set(task.abort_handle());
                }
                None => full(stream),
            },
            // Out of descriptors or the like: wait rather than spin.
            Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
        }
    }
}

/// A request or tunnel in progress on a connection: it is not idle while this lives.
pub(super) struct Busy(pub(super) Arc<Slot>);

impl Busy {
    pub(super) fn new(slot: Arc<Slot>) -> Self {
        slot.conn.busy.fetch_add(1, Ordering::Relaxed);
        slot.touch();
        Self(slot)
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        self.0.touch();
        self.0.conn.busy.fetch_sub(1, Ordering::Relaxed);
    }
}

/// A relayed side, marking its connection active whenever bytes come from it.
pub(super) struct Touch<T> {
    pub(super) inner: T,
    pub(super) slot: Arc<Slot>,
}

impl<T: AsyncRead + Unpin> AsyncRead for Touch<T> {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<std::io::Result<()>> {
        let r = Pin::new(&mut self.inner).poll_read(cx, buf);
        if r.is_ready() {
            self.slot.touch();
        }
        r
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for Touch<T> {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

//! The Unix-to-TCP relay: bytes both ways between the agent's MCP socket and the episode's server.
use super::*;

/// A running Unix-to-TCP relay; stopped by [`Relay::stop`] or when dropped.
pub struct Relay {
    running: Running,
}

impl Relay {
    /// Stops accepting, cuts the relayed connections and waits for the relay's thread.
    pub fn stop(mut self) {
        self.running.stop();
    }
}

/// Relays each connection accepted on `listener` to a new TCP connection to `target`, bytes both ways (a side's
/// end of stream is passed on as a half-close), until stopped. For the episode's MCP endpoint.
pub fn relay_unix_to_tcp(listener: StdUnixListener, target: SocketAddr) -> Result<Relay, GatewayError> {
    relay_unix_to_tcp_from(listener, target, None)
}

/// [`relay_unix_to_tcp`] with the outgoing connections bound to `source` (an address of this machine). Every
/// address of 127.0.0.0/8 is loopback on Linux without any set-up, so each agent's relay can come from an
/// address of its own and the server's per-address connection caps hold per agent, not for all agents at once.
/// Each connection is served by a task of its own; past [`MAX_CONNECTIONS`], a new one takes the place of the one
/// whose bytes moved last the longest ago.
pub fn relay_unix_to_tcp_from(listener: StdUnixListener, target: SocketAddr, source: Option<IpAddr>) -> Result<Relay, GatewayError> {
    relay_capped(listener, target, source, MAX_CONNECTIONS)
}

pub(super) fn relay_capped(listener: StdUnixListener, target: SocketAddr, source: Option<IpAddr>, max_connections: usize) -> Result<Relay, GatewayError> {
    let running = Running::spawn("netgate-relay", listener, move |listener| {
        let relay = move |stream: UnixStream, slot: Arc<Slot>| async move {
            if let Ok(Ok(tcp)) = tokio::time::timeout(CONNECT_TIMEOUT, connect_from(source, target)).await {
                let _ = tcp.set_nodelay(true);
                let mut client = Touch { inner: stream, slot: slot.clone() };
                let mut server = Touch { inner: tcp, slot };
                let _ = tokio::io::copy_bidirectional(&mut client, &mut server).await;
            }
        };
        // Every relayed connection can give its place up: there is always one to take.
        accept_loop(listener, max_connections, relay, drop)
    })?;
    Ok(Relay { running })
}

pub(super) async fn connect_from(source: Option<IpAddr>, target: SocketAddr) -> std::io::Result<TcpStream> {
    let Some(source) = source.filter(|s| s.is_ipv4() == target.is_ipv4()) else { return TcpStream::connect(target).await };
    let socket = if target.is_ipv4() { tokio::net::TcpSocket::new_v4()? } else { tokio::net::TcpSocket::new_v6()? };
    socket.bind(SocketAddr::new(source, 0))?;
    socket.connect(target).await
}

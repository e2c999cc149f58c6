//! What every server stream shares: one loop (`pump`) that waits for a stream's next message, sends
//! it, and ends the stream when its source is done, its client leaves or the server stops; and the
//! small pieces around it (the stop signal, ending with a status).
//!
//! The sample streams (SampleBatches, SampleBatchesShared), Act and dm_env_rpc's Process are each a
//! `Source` run by `pump`: only what they wait for and what they make differs.

use std::future::Future;
use std::time::Duration;

use tokio::sync::{mpsc, watch};
use tonic::Status;

use crate::error::ServiceError;

/// Ends the streams of a service: `stop()` when the server begins to shut down.
pub struct StreamStopper(pub(crate) watch::Sender<bool>);

impl StreamStopper {
    pub fn stop(&self) {
        self.0.send_replace(true);
    }
}

/// Resolves once `stopping` turns true (never, if its sender is gone without stopping).
pub(crate) async fn stopped(mut stopping: watch::Receiver<bool>) {
    if stopping.wait_for(|stop| *stop).await.is_err() {
        std::future::pending::<()>().await;
    }
}

/// What a stream sends, in two steps: `next` waits for what the next message comes from (the
/// client's next request, the producer's next batch) and may be cut short when the client leaves
/// or the server stops; `make` turns it into the message and always runs to its end (a request
/// the stream took is answered).
pub(crate) trait Source: Send {
    type Input: Send;
    type Message: Send + 'static;

    /// What the next message comes from; None: the stream is over; Err: it ends with that status.
    fn next(&mut self) -> impl Future<Output = Option<Result<Self::Input, Status>>> + Send;

    /// The message for `input`; Err ends the stream with that status.
    fn make(&mut self, input: Self::Input) -> impl Future<Output = Result<Self::Message, Status>> + Send;

    /// After a message was sent (a batch's metrics, once its last chunk went).
    fn sent(&mut self) {}
}

/// How a stream ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Ended {
    /// Its source had nothing more to send.
    Done,
    /// It ended with an error's status.
    Failed,
    /// Its client left (or stopped reading before the server stopped).
    Left,
    /// The server began to shut down; the client got the shutdown status.
    Stopped,
}

/// Runs a stream: sends what `source` makes until it is done, fails, the client leaves or the
/// server stops.
pub(crate) async fn pump<S: Source>(
    mut source: S,
    sender: &mpsc::Sender<Result<S::Message, Status>>,
    stopping: &watch::Receiver<bool>,
) -> Ended {
    loop {
        let input = tokio::select! {
            input = source.next() => input,
            // A client that leaves while the stream waits (for data, for its next request) frees it.
            () = sender.closed() => return Ended::Left,
            () = stopped(stopping.clone()) => {
                end_with_shutdown(sender).await;
                return Ended::Stopped;
            }
        };
        let message = match input {
            None => return Ended::Done,
            Some(Ok(input)) => source.make(input).await,
            Some(Err(status)) => Err(status),
        };
        let message = match message {
            Ok(message) => message,
            Err(status) => {
                let _ = sender.send(Err(status)).await;
                return Ended::Failed;
            }
        };
        if let Err(ended) = send_or_stop(sender, message, stopping).await {
            return ended;
        }
        source.sent();
    }
}

/// Ends a stream with the shutdown status; a client that does not read within a second misses it
/// (its stream then just ends: nothing it would read is lost).
pub(crate) async fn end_with_shutdown<T>(sender: &mpsc::Sender<Result<T, Status>>) {
    end_with(sender, ServiceError::StreamEnded).await;
}

/// Ends a stream with `error`'s status, unless its client does not read within a second.
pub(crate) async fn end_with<T>(sender: &mpsc::Sender<Result<T, Status>>, error: ServiceError) {
    let _ = tokio::time::timeout(Duration::from_secs(1), sender.send(Err(error.into()))).await;
}

/// Sends `item` unless the server stops or the client leaves first (how the stream ended, then).
async fn send_or_stop<T>(
    sender: &mpsc::Sender<Result<T, Status>>,
    item: T,
    stopping: &watch::Receiver<bool>,
) -> Result<(), Ended> {
    tokio::select! {
        sent = sender.send(Ok(item)) => sent.map_err(|_| Ended::Left),
        () = stopped(stopping.clone()) => {
            end_with_shutdown(sender).await;
            Err(Ended::Stopped)
        }
    }
}

/// A task that ends when this is dropped.
pub(crate) struct AbortOnDrop(pub(crate) tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Yields the numbers it was given, then ends (or fails, or waits forever).
    struct Numbers {
        left: Vec<u32>,
        then: Option<Status>,
        wait_forever: bool,
    }

    impl Source for Numbers {
        type Input = u32;
        type Message = u32;

        async fn next(&mut self) -> Option<Result<u32, Status>> {
            if let Some(number) = self.left.pop() {
                return Some(Ok(number));
            }
            match self.then.take() {
                Some(status) => Some(Err(status)),
                None if self.wait_forever => std::future::pending().await,
                None => None,
            }
        }

        async fn make(&mut self, input: u32) -> Result<u32, Status> {
            Ok(input * 10)
        }
    }

    async fn drain(mut receiver: mpsc::Receiver<Result<u32, Status>>) -> Vec<Result<u32, tonic::Code>> {
        let mut out = Vec::new();
        while let Some(item) = receiver.recv().await {
            out.push(item.map_err(|status| status.code()));
        }
        out
    }

    #[tokio::test]
    async fn a_source_is_sent_until_done_or_failed() {
        let (_stop, stopping) = watch::channel(false);
        let (sender, receiver) = mpsc::channel(8);
        let source = Numbers { left: vec![2, 1], then: None, wait_forever: false };
        assert_eq!(pump(source, &sender, &stopping).await, Ended::Done);
        drop(sender);
        assert_eq!(drain(receiver).await, vec![Ok(10), Ok(20)]);

        let (sender, receiver) = mpsc::channel(8);
        let source = Numbers { left: vec![3], then: Some(Status::invalid_argument("bad")), wait_forever: false };
        assert_eq!(pump(source, &sender, &stopping).await, Ended::Failed);
        drop(sender);
        assert_eq!(drain(receiver).await, vec![Ok(30), Err(tonic::Code::InvalidArgument)]);
    }

    #[tokio::test]
    async fn a_waiting_stream_ends_when_its_client_leaves_or_the_server_stops() {
        let (stop, stopping) = watch::channel(false);
        let (sender, receiver) = mpsc::channel(8);
        drop(receiver);
        let waiting = Numbers { left: Vec::new(), then: None, wait_forever: true };
        assert_eq!(pump(waiting, &sender, &stopping).await, Ended::Left);

        let (sender, receiver) = mpsc::channel(8);
        let waiting = Numbers { left: Vec::new(), then: None, wait_forever: true };
        let stopper = StreamStopper(stop);
        let pumped = tokio::spawn(async move { pump(waiting, &sender, &stopping).await });
        stopper.stop();
        assert_eq!(pumped.await.unwrap(), Ended::Stopped);
        assert_eq!(drain(receiver).await, vec![Err(Status::from(ServiceError::StreamEnded).code())]);
    }
}

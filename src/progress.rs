//! Progress on stderr: a bar when stderr is a terminal, else one log line
//! at intervals (a batch job's or a log file's stderr), so long work is
//! never silent for minutes and logs are not flooded with redraws.

use std::io::{IsTerminal, Write};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use indicatif::{
    HumanDuration, ProgressBar, ProgressDrawTarget, ProgressState, ProgressStyle, TermLike,
};

/// How often a progress line is logged when stderr is not a terminal.
pub const LOG_INTERVAL: Duration = Duration::from_secs(10);

/// A progress bar of `len` steps labelled `message`: drawn as a bar when
/// stderr is a terminal; otherwise a line `message: pos/len (…)` is logged
/// every [`LOG_INTERVAL`] while the work goes on (nothing for work that
/// ends sooner).
pub fn bar(len: u64, message: &str) -> ProgressBar {
    if std::io::stderr().is_terminal() {
        let bar = ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::stderr());
        bar.set_style(
            ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} ({per_sec}, eta {eta})")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .with_key("eta", eta)
                .progress_chars("=> "),
        );
        bar.set_message(message.to_string());
        bar
    } else {
        logged(len, message, LOG_INTERVAL, Box::new(std::io::stderr()))
    }
}

/// A progress bar that logs one line to `sink` at most every `interval`
/// (the first after `interval`), for stderr that is not a terminal.
pub fn logged(
    len: u64,
    message: &str,
    interval: Duration,
    sink: Box<dyn Write + Send>,
) -> ProgressBar {
    let lines = LogLines {
        interval,
        state: Mutex::new(LogState {
            sink,
            pending: String::new(),
            last: Instant::now(),
        }),
    };
    // One redraw a second at most; `LogLines` keeps one in `interval`.
    let bar = ProgressBar::with_draw_target(
        Some(len),
        ProgressDrawTarget::term_like_with_hz(Box::new(lines), 1),
    );
    bar.set_style(
        ProgressStyle::with_template("{msg}: {pos}/{len} ({percent}%, {per_sec}, eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .with_key("eta", eta),
    );
    bar.set_message(message.to_string());
    bar
}

/// The estimated time left, or `unknown` before the first step is done
/// (indicatif's own estimate says `0s` then, which reads as "finished").
fn eta(state: &ProgressState, out: &mut dyn std::fmt::Write) {
    let left = if state.pos() == 0 {
        "unknown".to_string()
    } else {
        format!("{:#}", HumanDuration(state.eta()))
    };
    // A failed write only loses a cosmetic field.
    let _ = out.write_str(&left);
}

/// A progress bar that never draws, for library callers and tests.
pub fn hidden() -> ProgressBar {
    ProgressBar::hidden()
}

/// indicatif's terminal, turned into a log: each redraw replaces the
/// pending line, and a flush writes it out if `interval` has passed since
/// the last line written.
struct LogLines {
    interval: Duration,
    state: Mutex<LogState>,
}

struct LogState {
    sink: Box<dyn Write + Send>,
    pending: String,
    last: Instant,
}

impl std::fmt::Debug for LogLines {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LogLines")
            .field("interval", &self.interval)
            .finish()
    }
}

impl LogLines {
    fn with_state(&self, act: impl FnOnce(&mut LogState)) -> std::io::Result<()> {
        // A poisoned lock only means a panic elsewhere; progress is cosmetic.
        let mut state = self.state.lock().unwrap_or_else(|p| p.into_inner());
        act(&mut state);
        Ok(())
    }
}

impl TermLike for LogLines {
    fn width(&self) -> u16 {
        160
    }

    fn move_cursor_up(&self, _n: usize) -> std::io::Result<()> {
        Ok(())
    }

    fn move_cursor_down(&self, _n: usize) -> std::io::Result<()> {
        Ok(())
    }

    fn move_cursor_right(&self, _n: usize) -> std::io::Result<()> {
        Ok(())
    }

    fn move_cursor_left(&self, _n: usize) -> std::io::Result<()> {
        Ok(())
    }

    fn write_line(&self, line: &str) -> std::io::Result<()> {
        self.write_str(line)
    }

    fn write_str(&self, text: &str) -> std::io::Result<()> {
        self.with_state(|state| {
            if !text.trim().is_empty() {
                state.pending = text.trim().to_string();
            }
        })
    }

    fn clear_line(&self) -> std::io::Result<()> {
        Ok(())
    }

    fn flush(&self) -> std::io::Result<()> {
        let interval = self.interval;
        self.with_state(|state| {
            if state.pending.is_empty() || state.last.elapsed() < interval {
                return;
            }
            // A closed stderr must not stop the work.
            let _ = writeln!(state.sink, "{}", state.pending);
            let _ = state.sink.flush();
            state.pending.clear();
            state.last = Instant::now();
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    /// A sink the test can read back.
    #[derive(Clone, Default)]
    struct Shared(Arc<Mutex<Vec<u8>>>);

    impl Write for Shared {
        fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
            self.0.lock().unwrap().extend_from_slice(bytes);
            Ok(bytes.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn logged_progress_writes_whole_lines_at_intervals_only() {
        let sink = Shared::default();
        let bar = logged(
            100,
            "locating",
            Duration::from_millis(300),
            Box::new(sink.clone()),
        );
        for _ in 0..5 {
            bar.inc(1);
        }
        // Within the first interval: nothing.
        assert!(sink.0.lock().unwrap().is_empty());
        std::thread::sleep(Duration::from_millis(1100));
        for _ in 0..5 {
            bar.inc(1);
        }
        std::thread::sleep(Duration::from_millis(1100));
        bar.inc(1);
        let text = String::from_utf8(sink.0.lock().unwrap().clone()).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert!(!lines.is_empty(), "no progress line in {text:?}");
        assert!(lines.len() <= 3, "too many lines: {text:?}");
        for line in &lines {
            assert!(line.starts_with("locating: "), "{line:?}");
            assert!(line.contains("/100"), "{line:?}");
            assert!(!line.contains('\r') && !line.contains('\x1b'), "{line:?}");
        }
    }

    #[test]
    fn the_time_left_is_unknown_until_a_step_is_done() {
        let sink = Shared::default();
        let bar = logged(5, "tasks done", Duration::ZERO, Box::new(sink.clone()));
        bar.tick();
        std::thread::sleep(Duration::from_millis(1100));
        bar.tick();
        let text = String::from_utf8(sink.0.lock().unwrap().clone()).unwrap();
        let first = text.lines().next().expect("a progress line");
        assert!(
            first.contains("0/5") && first.ends_with("eta unknown)"),
            "{first:?}"
        );
    }
}

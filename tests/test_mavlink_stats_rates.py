"""Link rates in the sender's clock (mavlink_io/stats.py): a busy daemon reads bursts late, one
receive time for many messages; the FC stamps still say how fast the FC sends."""
from mavlink_io.stats import LinkStats


def test_given_a_burst_read_at_one_receive_time_then_the_rate_is_the_fc_rate():
    st = LinkStats(rate_window_s=2.0)
    for k in range(800):                     # 2 s of 400 Hz RAW_IMU, read in 4 bursts of 0.5 s
        st.count_message("RAW_IMU", rx_s=100.0 + 0.5 * (k // 200), fc_s=10.0 + k / 400.0)
    assert abs(st.rates_hz()["RAW_IMU"] - 400.0) < 1.0


def test_given_no_stamp_then_the_local_rate_and_a_dead_stream_reads_zero():
    st = LinkStats(rate_window_s=2.0)
    for k in range(21):
        st.count_message("HEARTBEAT", rx_s=100.0 + k)        # no FC stamp: local time, 1 Hz
        st.count_message("ATTITUDE", rx_s=100.0 + k, fc_s=5.0 + 0.02 * k)
    r = st.rates_hz()
    assert abs(r["HEARTBEAT"] - 1.0) < 1e-9 and abs(r["ATTITUDE"] - 50.0) < 1e-6
    st.set_now(125.0)                                       # nothing for 5 s of local time
    assert st.rates_hz()["ATTITUDE"] == 0.0 and st.rates_hz()["HEARTBEAT"] == 0.0


def test_an_fc_reboot_restarts_the_fc_window():
    st = LinkStats(rate_window_s=2.0)
    for k in range(100):
        st.count_message("RAW_IMU", rx_s=100.0 + k * 0.01, fc_s=500.0 + k * 0.01)
    for k in range(50):                      # the FC restarted its clock near zero
        st.count_message("RAW_IMU", rx_s=101.0 + k * 0.01, fc_s=0.2 + k * 0.01)
    assert abs(st.rates_hz()["RAW_IMU"] - 100.0) < 1e-6

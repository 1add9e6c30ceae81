//! The shipped device templates (config/templates/) against the simulated devices they were
//! made for, each in a known state: every value the template lists, read by the gateway's polls,
//! is what the device holds there, in the template's units. The figures are worked out from the
//! manuals' scaling and the simulator's models (the drives' motor tables, the meter's formulas),
//! as `tests/templates_expected.md` works them out register by register.

use crate::support::{http_get, within, Bus, GatewayConfig, RawMaster};
use std::collections::BTreeMap;
use std::time::Duration;

/// Write 0001H to 2000H: run forward (the Goodrive and Pd-series control word).
const RUN: [u8; 5] = [0x06, 0x20, 0x00, 0x00, 0x01];

/// The gateway with the simulated device `model` at unit 1 (its `[[bus.sim_slave]]` keys
/// `sim`), exporting `template`'s values every 100 ms, its `[[bus.slave]]` keys `slave` too.
async fn gateway(template: &str, slave: &str, model: &str, sim: &str) -> modbus_gateway::Gateway {
    let text = format!(
        "[[bus.slave]]\naddress = 1\ntemplate = \"{template}\"\npoll_interval = \"100ms\"\n{slave}\n\
         [[bus.sim_slave]]\naddress = 1\nmodel = \"{model}\"\n{sim}\n"
    );
    GatewayConfig::new()
        .listen("127.0.0.1:0")
        .bus(
            Bus::on("line", "sim")
                .baud(115_200)
                .parity("none")
                .text(&text),
        )
        .start()
        .await
}

/// Unit 1's values as `GET /values` lists them, once every one has been read.
async fn read_once(gateway: &modbus_gateway::Gateway) -> Option<BTreeMap<String, f64>> {
    let (status, body) = http_get(gateway.metrics_addr(), "/values?slave=1").await;
    assert_eq!(status, 200, "{body}");
    let listing: serde_json::Value = serde_json::from_str(&body).unwrap();
    listing["values"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| Some((v["name"].as_str()?.to_owned(), v["value"].as_f64()?)))
        .collect()
}

/// Every value of unit 1 once two listings in a row agree and every value has been read.
async fn settled(gateway: &modbus_gateway::Gateway) -> BTreeMap<String, f64> {
    within("the template's values settle", async {
        let mut last = BTreeMap::new();
        loop {
            tokio::time::sleep(Duration::from_millis(150)).await;
            match read_once(gateway).await {
                Some(now) if now == last => return now,
                Some(now) => last = now,
                None => last.clear(),
            }
        }
    })
    .await
}

/// `got` holds exactly `expected`'s values, each as raw x scale in f64 (hence the tolerance).
fn assert_values(what: &str, got: &BTreeMap<String, f64>, expected: &[(&str, f64)]) {
    let names: Vec<&str> = got.keys().map(String::as_str).collect();
    let mut wanted: Vec<&str> = expected.iter().map(|(n, _)| *n).collect();
    wanted.sort_unstable();
    assert_eq!(names, wanted, "{what}: the template's values");
    for (name, value) in expected {
        let read = got[*name];
        assert!(
            (read - value).abs() <= 1e-9 * value.abs().max(1.0),
            "{what}: {name} is {read}, not {value}"
        );
    }
}

/// Run unit 1 forward, as a master would.
async fn run(gateway: &modbus_gateway::Gateway) {
    let mut master = RawMaster::connect(crate::support::addr(gateway)).await;
    assert_eq!(master.call(1, 1, &RUN).await, RUN);
}

#[tokio::test]
async fn goodrive20_reads_its_state_and_running_values_stopped_and_at_50_hz() {
    let stopped = gateway("goodrive20", "", "gd20", "").await;
    assert_values("GD20 stopped", &settled(&stopped).await, GD20_POWER_ON);
    let running = gateway(
        "goodrive20",
        "",
        "gd20",
        "params = { \"P00.01\" = 2, \"P00.11\" = 0 }",
    )
    .await;
    run(&running).await;
    assert_values("GD20 at 50 Hz", &settled(&running).await, GD20_RUNNING);
}

#[tokio::test]
async fn goodrive300_reads_its_state_and_running_values_stopped_and_at_50_hz() {
    let stopped = gateway("goodrive300", "", "gd300", "").await;
    assert_values("GD300 stopped", &settled(&stopped).await, GD300_POWER_ON);
    let running = gateway(
        "goodrive300",
        "",
        "gd300",
        "params = { \"P00.01\" = 2, \"P00.11\" = 0 }",
    )
    .await;
    run(&running).await;
    assert_values("GD300 at 50 Hz", &settled(&running).await, GD300_RUNNING);
}

#[tokio::test]
async fn goodrive10_reads_its_fault_when_tripped_and_its_running_values_at_50_hz() {
    let tripped = gateway("goodrive10", "", "gd10", "trip = 35").await;
    assert_values("GD10 tripped", &settled(&tripped).await, GD10_TRIPPED);
    let running = gateway(
        "goodrive10",
        "",
        "gd10",
        "params = { \"P00.01\" = 2, \"P00.11\" = 0 }",
    )
    .await;
    run(&running).await;
    assert_values("GD10 at 50 Hz", &settled(&running).await, GD10_RUNNING);
}

#[tokio::test]
async fn pd_inverter_reads_its_running_values_in_either_read_form_and_its_fault() {
    let stopped = gateway(
        "pd-inverter",
        "",
        "pd-inverter",
        "params = { \"Pd-05\" = 1 }",
    )
    .await;
    assert_values("Pd stopped", &settled(&stopped).await, PD_POWER_ON);
    // The factory "non-standard" replies, read with wide_read_count as the demo's unit 4.
    let running = gateway(
        "pd-inverter",
        "wide_read_count = true",
        "pd-inverter",
        "params = { \"P0-02\" = 2, \"P0-17\" = 0 }",
    )
    .await;
    run(&running).await;
    assert_values("Pd at 50 Hz", &settled(&running).await, PD_RUNNING);
    let tripped = gateway(
        "pd-inverter",
        "",
        "pd-inverter",
        "params = { \"Pd-05\" = 1 }\ntrip = 16",
    )
    .await;
    assert_values("Pd tripped", &settled(&tripped).await, PD_TRIPPED);
}

#[tokio::test]
async fn eastron_sdm120_reads_the_meters_floats_in_their_units_near_power_on() {
    let meter = gateway("eastron-sdm120", "", "sdm120", "").await;
    // The meter's values move with time from power-on (230 V, 5 A, 1150 W, PF 1, 50 Hz, no
    // energy yet): within the first seconds each lies in a narrow band around them.
    let got = within("the meter's values", async {
        loop {
            if let Some(read) = read_once(&meter).await {
                return read;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    for (name, low, high) in [
        ("energy_meter_voltage_volts", 229.99, 230.3),
        ("energy_meter_current_amperes", 4.99, 5.1),
        ("energy_meter_active_power_watts", 1149.9, 1170.0),
        ("energy_meter_apparent_power_volt_amperes", 1149.9, 1170.0),
        (
            "energy_meter_reactive_power_volt_amperes_reactive",
            0.0,
            0.5,
        ),
        ("energy_meter_power_factor", 0.9999, 1.0),
        ("energy_meter_phase_angle_radians", 0.0, 0.001),
        ("energy_meter_frequency_hertz", 49.999, 50.02),
        // About 1150 J a second since power-on; the register holds kWh.
        ("energy_meter_import_active_energy_joules", 0.0, 12_000.0),
        ("energy_meter_export_active_energy_joules", 0.0, 0.0),
        (
            "energy_meter_import_reactive_energy_volt_ampere_reactive_seconds",
            0.0,
            1.0,
        ),
        (
            "energy_meter_export_reactive_energy_volt_ampere_reactive_seconds",
            0.0,
            0.0,
        ),
        ("energy_meter_total_active_energy_joules", 0.0, 12_000.0),
        (
            "energy_meter_total_reactive_energy_volt_ampere_reactive_seconds",
            0.0,
            1.0,
        ),
    ] {
        let value = got.get(name).copied().unwrap_or(f64::NAN);
        assert!(
            (low..=high).contains(&value),
            "{name} is {value}, not in {low}..={high}"
        );
    }
    assert_eq!(got.len(), 14, "every value of the template: {got:?}");
}

/// goodrive20 right after power-on, stopped, factory parameters.
const GD20_POWER_ON: &[(&str, f64)] = &[
    ("drive_state", 3.0),
    ("drive_ready", 1.0),
    ("drive_overload_prealarm", 0.0),
    ("drive_terminal_control", 0.0),
    ("drive_communication_control", 0.0),
    ("drive_fault_code", 0.0),
    ("drive_identifying_code", 262.0),
    ("drive_output_frequency_hertz", 0.0),
    ("drive_reference_frequency_hertz", 50.0),
    ("drive_dc_bus_voltage_volts", 311.0),
    ("drive_output_voltage_volts", 0.0),
    ("drive_output_current_amperes", 0.0),
    ("drive_motor_speed_revolutions_per_minute", 0.0),
    ("drive_output_power_ratio", 0.0),
    ("drive_output_torque_ratio", 0.0),
    ("drive_pid_reference_ratio", 0.0),
    ("drive_pid_feedback_ratio", 0.0),
    ("drive_input_terminals_state", 0.0),
    ("drive_output_terminals_state", 0.0),
    ("drive_analog_input_1_volts", 0.0),
    ("drive_analog_input_2_volts", 0.0),
    ("drive_analog_input_3_volts", 0.0),
    ("drive_analog_input_4_volts", 0.0),
    ("drive_pulse_input_frequency_hertz", 0.0),
    ("drive_multi_step_speed_step", 0.0),
    ("drive_external_length", 0.0),
    ("drive_external_counting_value", 0.0),
    ("drive_torque_reference_ratio", 0.0),
];
/// goodrive20 running forward at 50.00 Hz under communication control, the ramp over.
const GD20_RUNNING: &[(&str, f64)] = &[
    ("drive_state", 1.0),
    ("drive_ready", 1.0),
    ("drive_overload_prealarm", 0.0),
    ("drive_terminal_control", 0.0),
    ("drive_communication_control", 1.0),
    ("drive_fault_code", 0.0),
    ("drive_identifying_code", 262.0),
    ("drive_output_frequency_hertz", 50.0),
    ("drive_reference_frequency_hertz", 50.0),
    ("drive_dc_bus_voltage_volts", 311.0),
    ("drive_output_voltage_volts", 220.0),
    ("drive_output_current_amperes", 2.9),
    ("drive_motor_speed_revolutions_per_minute", 1400.0),
    ("drive_output_power_ratio", 0.8),
    ("drive_output_torque_ratio", 0.8),
    ("drive_pid_reference_ratio", 0.0),
    ("drive_pid_feedback_ratio", 0.0),
    ("drive_input_terminals_state", 0.0),
    ("drive_output_terminals_state", 0.0),
    ("drive_analog_input_1_volts", 0.0),
    ("drive_analog_input_2_volts", 0.0),
    ("drive_analog_input_3_volts", 0.0),
    ("drive_analog_input_4_volts", 0.0),
    ("drive_pulse_input_frequency_hertz", 0.0),
    ("drive_multi_step_speed_step", 0.0),
    ("drive_external_length", 0.0),
    ("drive_external_counting_value", 0.0),
    ("drive_torque_reference_ratio", 0.0),
];
/// goodrive300 right after power-on.
const GD300_POWER_ON: &[(&str, f64)] = &[
    ("drive_state", 3.0),
    ("drive_ready", 1.0),
    ("drive_overload_prealarm", 0.0),
    ("drive_terminal_control", 0.0),
    ("drive_communication_control", 0.0),
    ("drive_fault_code", 0.0),
    ("drive_identifying_code", 266.0),
    ("drive_output_frequency_hertz", 0.0),
    ("drive_reference_frequency_hertz", 50.0),
    ("drive_dc_bus_voltage_volts", 540.0),
    ("drive_output_voltage_volts", 0.0),
    ("drive_output_current_amperes", 0.0),
    ("drive_motor_speed_revolutions_per_minute", 0.0),
    ("drive_output_power_ratio", 0.0),
    ("drive_output_torque_ratio", 0.0),
    ("drive_pid_reference_ratio", 0.0),
    ("drive_pid_feedback_ratio", 0.0),
    ("drive_input_terminals_state", 0.0),
    ("drive_output_terminals_state", 0.0),
    ("drive_analog_input_1_volts", 0.0),
    ("drive_analog_input_2_volts", 0.0),
    ("drive_analog_input_3_volts", 0.0),
    ("drive_pulse_input_frequency_hertz", 0.0),
    ("drive_multi_step_speed_step", 0.0),
    ("drive_external_length", 0.0),
    ("drive_external_counting_value", 0.0),
    ("drive_torque_reference_ratio", 0.0),
    ("drive_frequency_setpoint_hertz", 0.0),
];
/// goodrive300 running forward at 50.00 Hz.
const GD300_RUNNING: &[(&str, f64)] = &[
    ("drive_state", 1.0),
    ("drive_ready", 1.0),
    ("drive_overload_prealarm", 0.0),
    ("drive_terminal_control", 0.0),
    ("drive_communication_control", 1.0),
    ("drive_fault_code", 0.0),
    ("drive_identifying_code", 266.0),
    ("drive_output_frequency_hertz", 50.0),
    ("drive_reference_frequency_hertz", 50.0),
    ("drive_dc_bus_voltage_volts", 540.0),
    ("drive_output_voltage_volts", 380.0),
    ("drive_output_current_amperes", 11.1),
    ("drive_motor_speed_revolutions_per_minute", 1440.0),
    ("drive_output_power_ratio", 0.8),
    ("drive_output_torque_ratio", 0.8),
    ("drive_pid_reference_ratio", 0.0),
    ("drive_pid_feedback_ratio", 0.0),
    ("drive_input_terminals_state", 0.0),
    ("drive_output_terminals_state", 0.0),
    ("drive_analog_input_1_volts", 0.0),
    ("drive_analog_input_2_volts", 0.0),
    ("drive_analog_input_3_volts", 0.0),
    ("drive_pulse_input_frequency_hertz", 0.0),
    ("drive_multi_step_speed_step", 0.0),
    ("drive_external_length", 0.0),
    ("drive_external_counting_value", 0.0),
    ("drive_torque_reference_ratio", 0.0),
    ("drive_frequency_setpoint_hertz", 0.0),
];
/// goodrive10 running forward at 50.00 Hz.
const GD10_RUNNING: &[(&str, f64)] = &[
    ("drive_state", 1.0),
    ("drive_ready", 1.0),
    ("drive_overload_prealarm", 0.0),
    ("drive_terminal_control", 0.0),
    ("drive_communication_control", 1.0),
    ("drive_fault_code", 0.0),
    ("drive_identifying_code", 269.0),
    ("drive_output_frequency_hertz", 50.0),
    ("drive_reference_frequency_hertz", 50.0),
    ("drive_dc_bus_voltage_volts", 311.0),
    ("drive_output_voltage_volts", 220.0),
    ("drive_output_current_amperes", 1.9),
    ("drive_motor_speed_revolutions_per_minute", 1390.0),
    ("drive_output_power_ratio", 0.8),
    ("drive_output_torque_ratio", 0.8),
    ("drive_pid_reference_ratio", 0.0),
    ("drive_pid_feedback_ratio", 0.0),
    ("drive_input_terminals_state", 0.0),
    ("drive_output_terminals_state", 0.0),
    ("drive_analog_input_1_volts", 0.0),
    ("drive_analog_input_2_volts", 0.0),
    ("drive_external_counting_value", 0.0),
    ("drive_torque_reference_ratio", 0.0),
    ("drive_frequency_setpoint_hertz", 0.0),
];
/// goodrive10 tripped on fault 35 (STo) at power-on.
const GD10_TRIPPED: &[(&str, f64)] = &[
    ("drive_state", 4.0),
    ("drive_ready", 1.0),
    ("drive_overload_prealarm", 0.0),
    ("drive_terminal_control", 0.0),
    ("drive_communication_control", 0.0),
    ("drive_fault_code", 35.0),
    ("drive_identifying_code", 269.0),
    ("drive_output_frequency_hertz", 0.0),
    ("drive_reference_frequency_hertz", 50.0),
    ("drive_dc_bus_voltage_volts", 311.0),
    ("drive_output_voltage_volts", 0.0),
    ("drive_output_current_amperes", 0.0),
    ("drive_motor_speed_revolutions_per_minute", 0.0),
    ("drive_output_power_ratio", 0.0),
    ("drive_output_torque_ratio", 0.0),
    ("drive_pid_reference_ratio", 0.0),
    ("drive_pid_feedback_ratio", 0.0),
    ("drive_input_terminals_state", 0.0),
    ("drive_output_terminals_state", 0.0),
    ("drive_analog_input_1_volts", 0.0),
    ("drive_analog_input_2_volts", 0.0),
    ("drive_external_counting_value", 0.0),
    ("drive_torque_reference_ratio", 0.0),
    ("drive_frequency_setpoint_hertz", 0.0),
];
/// pd-inverter right after power-on (Pd-05 = 1: standard read replies).
const PD_POWER_ON: &[(&str, f64)] = &[
    ("drive_state", 3.0),
    ("drive_fault_code", 0.0),
    ("drive_communication_setting_ratio", 0.0),
    ("drive_output_frequency_hertz", 0.0),
    ("drive_dc_bus_voltage_volts", 540.0),
    ("drive_output_voltage_volts", 0.0),
    ("drive_output_current_amperes", 0.0),
    ("drive_output_power_watts", 0.0),
    ("drive_output_torque_ratio", 0.0),
    ("drive_motor_speed_revolutions_per_minute", 0.0),
    ("drive_input_terminals_state", 0.0),
    ("drive_output_terminals_state", 0.0),
    ("drive_external_counting_value", 0.0),
    ("drive_external_length", 0.0),
    ("drive_plc_step", 0.0),
    ("drive_feedback_speed_hertz", 0.0),
    ("drive_power_on_time_seconds", 0.0),
    ("drive_running_time_seconds", 0.0),
    ("drive_pulse_input_frequency_hertz", 0.0),
    ("drive_main_frequency_reference_hertz", 50.0),
];
/// pd-inverter running forward at 50.00 Hz, within its first minute (its minute counters 0).
const PD_RUNNING: &[(&str, f64)] = &[
    ("drive_state", 1.0),
    ("drive_fault_code", 0.0),
    ("drive_communication_setting_ratio", 0.0),
    ("drive_output_frequency_hertz", 50.0),
    ("drive_dc_bus_voltage_volts", 540.0),
    ("drive_output_voltage_volts", 380.0),
    ("drive_output_current_amperes", 4.39),
    ("drive_output_power_watts", 1800.0),
    ("drive_output_torque_ratio", 0.8),
    ("drive_motor_speed_revolutions_per_minute", 1430.0),
    ("drive_input_terminals_state", 0.0),
    ("drive_output_terminals_state", 0.0),
    ("drive_external_counting_value", 0.0),
    ("drive_external_length", 0.0),
    ("drive_plc_step", 0.0),
    ("drive_feedback_speed_hertz", 50.0),
    ("drive_power_on_time_seconds", 0.0),
    ("drive_running_time_seconds", 0.0),
    ("drive_pulse_input_frequency_hertz", 0.0),
    ("drive_main_frequency_reference_hertz", 50.0),
];
/// pd-inverter tripped on fault 16 (communication abnormality) at power-on.
const PD_TRIPPED: &[(&str, f64)] = &[
    ("drive_state", 3.0),
    ("drive_fault_code", 16.0),
    ("drive_communication_setting_ratio", 0.0),
    ("drive_output_frequency_hertz", 0.0),
    ("drive_dc_bus_voltage_volts", 540.0),
    ("drive_output_voltage_volts", 0.0),
    ("drive_output_current_amperes", 0.0),
    ("drive_output_power_watts", 0.0),
    ("drive_output_torque_ratio", 0.0),
    ("drive_motor_speed_revolutions_per_minute", 0.0),
    ("drive_input_terminals_state", 0.0),
    ("drive_output_terminals_state", 0.0),
    ("drive_external_counting_value", 0.0),
    ("drive_external_length", 0.0),
    ("drive_plc_step", 0.0),
    ("drive_feedback_speed_hertz", 0.0),
    ("drive_power_on_time_seconds", 0.0),
    ("drive_running_time_seconds", 0.0),
    ("drive_pulse_input_frequency_hertz", 0.0),
    ("drive_main_frequency_reference_hertz", 50.0),
];

"""A separate rclpy process that reads parameters of a node and prints them as JSON.

    python get_params.py NODE NAME [NAME ...]
"""
import json
import sys

import rclpy
from rcl_interfaces.srv import GetParameters
from rclpy.parameter import parameter_value_to_python


def main():
    node_name, names = sys.argv[1], sys.argv[2:]
    rclpy.init()
    node = rclpy.create_node("test_get_params")
    client = node.create_client(GetParameters, f"{node_name}/get_parameters")
    if not client.wait_for_service(timeout_sec=30):
        print("no service")
        sys.exit(1)
    future = client.call_async(GetParameters.Request(names=names))
    rclpy.spin_until_future_complete(node, future, timeout_sec=20)
    values = [parameter_value_to_python(v) for v in future.result().values]
    print(json.dumps(dict(zip(names, values))), flush=True)
    rclpy.shutdown()


if __name__ == "__main__":
    main()

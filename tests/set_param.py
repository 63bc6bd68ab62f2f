"""A separate rclpy process that sets one parameter of a node and prints the result.

    python set_param.py NODE NAME VALUE_AS_PYTHON_LITERAL
prints 'ok' or 'rejected: <reason>'; exit 0 when the call was answered.
"""
import ast
import sys

import rclpy
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter


def main():
    node_name, name, value = sys.argv[1], sys.argv[2], ast.literal_eval(sys.argv[3])
    rclpy.init()
    node = rclpy.create_node("test_set_param")
    client = node.create_client(SetParameters, f"{node_name}/set_parameters")
    if not client.wait_for_service(timeout_sec=20):
        print("no service")
        sys.exit(1)
    req = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
    future = client.call_async(req)
    rclpy.spin_until_future_complete(node, future, timeout_sec=20)
    result = future.result().results[0]
    print("ok" if result.successful else f"rejected: {result.reason}", flush=True)
    rclpy.shutdown()


if __name__ == "__main__":
    main()

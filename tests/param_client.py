"""A separate rclpy process that reads or sets parameters of a node over its services.

    python param_client.py get NODE NAME [NAME ...]   prints {name: value} as JSON
    python param_client.py set NODE NAME VALUE        VALUE a Python literal; prints 'ok' or
                                                      'rejected: <reason>'
Exit 0 when the call was answered. Used through conftest.get_params / conftest.set_param.
"""
import ast
import json
import sys

import rclpy
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.parameter import Parameter, parameter_value_to_python


def call(node, srv_type, service: str, request):
    client = node.create_client(srv_type, service)
    if not client.wait_for_service(timeout_sec=30):
        print("no service")
        sys.exit(1)
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=20)
    return future.result()


def main():
    verb, node_name, args = sys.argv[1], sys.argv[2], sys.argv[3:]
    rclpy.init()
    node = rclpy.create_node("test_param_client")
    if verb == "get":
        result = call(node, GetParameters, f"{node_name}/get_parameters",
                      GetParameters.Request(names=args))
        values = [parameter_value_to_python(v) for v in result.values]
        print(json.dumps(dict(zip(args, values))), flush=True)
    else:
        name, value = args[0], ast.literal_eval(args[1])
        request = SetParameters.Request(
            parameters=[Parameter(name, value=value).to_parameter_msg()])
        result = call(node, SetParameters, f"{node_name}/set_parameters", request).results[0]
        print("ok" if result.successful else f"rejected: {result.reason}", flush=True)
    rclpy.shutdown()


if __name__ == "__main__":
    main()
